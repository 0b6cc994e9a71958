"""Board detections of every camera, from a video file, a folder of images or a glob."""

from __future__ import annotations

import glob
from dataclasses import dataclass, field
from pathlib import Path
from typing import Iterator

import cv2
import numpy as np
from tqdm import tqdm

from ..errors import CalibrationError
from .boards import Board, Detection

IMAGE_EXTS = {".png", ".jpg", ".jpeg", ".bmp", ".tif", ".tiff"}
VIDEO_EXTS = {".mp4", ".avi", ".mkv", ".mov", ".webm", ".m4v"}


@dataclass
class CameraViews:
    """Detections of one camera: `views[frame] = Detection` (frames are synchronized indices)."""

    name: str
    size: tuple[int, int]  # (width, height)
    views: dict[int, Detection] = field(default_factory=dict)
    frames_read: int = 0
    max_corners: int = 0  # most board corners found in any frame (also below the minimum)
    max_markers: int = 0
    mirrored_views: int = 0

    def usable(self, min_corners: int) -> dict[int, Detection]:
        return {f: d for f, d in self.views.items() if len(d.ids) >= min_corners}


def iter_frames(path: str | Path, every: int = 1, max_frames: int | None = None) -> Iterator[tuple[int, np.ndarray]]:
    """(frame index, grayscale image) of a video file, an image folder or a glob pattern."""
    p = Path(path)
    every = max(1, int(every))
    if p.is_file() and p.suffix.lower() in VIDEO_EXTS:
        cap = cv2.VideoCapture(str(p))
        if not cap.isOpened():
            raise CalibrationError(f"cannot open video {p}")
        try:
            idx = n = 0
            while max_frames is None or n < max_frames:
                if idx % every:
                    if not cap.grab():
                        break
                else:
                    ok, img = cap.read()
                    if not ok:
                        break
                    yield idx, cv2.cvtColor(img, cv2.COLOR_BGR2GRAY)
                    n += 1
                idx += 1
        finally:
            cap.release()
        return
    if p.is_dir():
        files = sorted(f for f in p.iterdir() if f.suffix.lower() in IMAGE_EXTS)
    elif p.is_file():
        files = [p]
    else:
        files = sorted(Path(f) for f in glob.glob(str(path)) if Path(f).suffix.lower() in IMAGE_EXTS)
    if not files:
        raise CalibrationError(f"no images or video found at {path}")
    for i, f in enumerate(files[::every][:max_frames]):
        img = cv2.imread(str(f), cv2.IMREAD_GRAYSCALE)
        if img is None:
            raise CalibrationError(f"cannot read image {f}")
        yield i * every, img


def detect_camera(name: str, path: str | Path, board: Board, every: int = 1, max_frames: int | None = None,
                  offset: int = 0, progress: bool = True) -> CameraViews:
    """Detect the board in every (every-th) frame of one camera; frame keys get `offset` added."""
    out: CameraViews | None = None
    frames = iter_frames(path, every, max_frames)
    for idx, gray in tqdm(frames, desc=f"detect {name}", unit="frame", disable=not progress, leave=False):
        size = (gray.shape[1], gray.shape[0])
        if out is None:
            out = CameraViews(name, size)
        elif size != out.size:
            raise CalibrationError(f"camera {name}: frame {idx} is {size[0]}x{size[1]}, earlier frames {out.size[0]}x{out.size[1]}")
        out.frames_read += 1
        det = board.detect(gray)
        if det is None:
            continue
        out.max_corners = max(out.max_corners, len(det.ids))
        out.max_markers = max(out.max_markers, det.markers)
        if len(det.ids):
            out.views[idx + offset] = det
            out.mirrored_views += int(det.mirrored)
    if out is None:
        raise CalibrationError(f"camera {name}: no frames in {path}")
    return out


def explain_no_board(cam: CameraViews, board: Board) -> str:
    """Why a camera has no usable view, for the CalibrationError message."""
    what = f"in {cam.frames_read} frames"
    if cam.max_corners == 0:
        extra = f" (at most {cam.max_markers} of its ArUco markers decoded)" if board.kind == "charuco" else ""
        return f"the board ({board.describe()}) was never detected {what}{extra}"
    return (f"at most {cam.max_corners} board corners were found in one frame {what}; "
            f"at least {board.min_corners} are needed")
