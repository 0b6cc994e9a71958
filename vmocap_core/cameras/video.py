"""Video files as camera sources: one file per camera, synchronized by frame index.

Stamps come from the frame index and the frame rate (not from the decoder's clock), so N
files recorded together give identical stamps for simultaneous frames. A per-camera frame
offset aligns files that started at different moments: with `offset_frames=k`, file frame
`k` is logical frame 0 (k < 0: the file starts |k| frames late).
"""

from __future__ import annotations

import time
from pathlib import Path

import cv2
import numpy as np

from ..errors import SourceError
from .base import Frame, FrameSource


class VideoFrameSource(FrameSource):
    """Frames of one video file (any format OpenCV's FFmpeg backend reads).

    fps: override the file's frame rate. start_ns: stamp of logical frame 0. realtime: pace
    `read` at the frame rate like a live camera. trigger_mode: `read` returns a frame only
    after `trigger()` (one per trigger), for rehearsing software-triggered rigs.
    mono: deliver (H, W) grayscale. flip: 'h' / 'v' / 'hv' mirror the image (mirrored webcams).
    """

    def __init__(self, path: str | Path, camera: str | None = None, fps: float | None = None,
                 offset_frames: int = 0, start_ns: int = 0, loop: bool = False, realtime: bool = False,
                 trigger_mode: bool = False, mono: bool = False, flip: str = "") -> None:
        self.path = Path(path)
        self.name = camera or self.path.stem
        self._fps_override = fps
        self.offset_frames = int(offset_frames)
        self.start_ns = int(start_ns)
        self.loop = loop
        self.realtime = realtime
        self.software_trigger = bool(trigger_mode)
        self.mono = mono
        if flip not in ("", "h", "v", "hv"):
            raise SourceError(f"camera {self.name}: flip must be '', 'h', 'v' or 'hv', not '{flip}'")
        self.flip = flip
        self._cap: cv2.VideoCapture | None = None
        self._file_index = 0
        self._loops = 0
        self._loop_base = 0
        self._pass_frames = 0
        self._done = False
        self._pending = 0
        self._t0: float | None = None
        self._size: tuple[int, int] | None = None
        self.fps = 0.0
        self.frame_count = 0
        self._delivered = 0

    def open(self) -> None:
        if not self.path.is_file():
            raise SourceError(f"camera {self.name}: video file {self.path} does not exist")
        cap = cv2.VideoCapture(str(self.path))
        if not cap.isOpened():
            raise SourceError(f"camera {self.name}: cannot decode video {self.path}")
        self._cap = cap
        self.fps = float(self._fps_override or cap.get(cv2.CAP_PROP_FPS) or 0.0)
        if not self.fps > 0:
            self.close()
            raise SourceError(f"camera {self.name}: {self.path} gives no frame rate; pass fps")
        self.frame_count = int(cap.get(cv2.CAP_PROP_FRAME_COUNT) or 0)
        self._size = (int(cap.get(cv2.CAP_PROP_FRAME_WIDTH)), int(cap.get(cv2.CAP_PROP_FRAME_HEIGHT)))
        self._file_index = 0
        self._loops = self._loop_base = self._pass_frames = 0
        self._done = False
        self._skip_to(max(0, self.offset_frames))

    def _skip_to(self, index: int) -> None:
        assert self._cap is not None
        while self._file_index < index:
            if not self._cap.grab():
                self._done = True
                return
            self._file_index += 1

    def close(self) -> None:
        if self._cap is not None:
            self._cap.release()
            self._cap = None

    @property
    def exhausted(self) -> bool:
        return self._done

    @property
    def size(self) -> tuple[int, int] | None:
        return self._size

    @property
    def period_ns(self) -> int:
        return int(round(1e9 / self.fps)) if self.fps > 0 else 0

    def trigger(self) -> None:
        if not self.software_trigger:
            raise SourceError(f"camera {self.name}: not in trigger mode")
        self._pending += 1

    def stamp_of(self, logical_index: int) -> int:
        """Stamp (ns) of a logical frame index: start_ns + index / fps."""
        return self.start_ns + int(round(logical_index * 1e9 / self.fps))

    def read(self, timeout: float = 1.0) -> Frame | None:
        if self._cap is None:
            raise SourceError(f"camera {self.name}: read before open")
        if self.software_trigger:
            if self._pending == 0:
                time.sleep(min(timeout, 0.001))
                return None
            self._pending -= 1
        if self._done:
            return None
        ok, img = self._cap.read()
        if not ok and self.loop and self._pass_frames > 0:
            # start over; logical indices (and stamps) keep increasing across passes
            self._loop_base += self._pass_frames
            self._pass_frames = 0
            self._loops += 1
            self._cap.set(cv2.CAP_PROP_POS_FRAMES, 0)
            self._file_index = 0
            self._skip_to(max(0, self.offset_frames))
            ok, img = self._cap.read()
        if not ok:
            self._done = True
            return None
        logical = self._loop_base + self._file_index - self.offset_frames
        self._file_index += 1
        self._pass_frames += 1
        if self.realtime:
            self._pace(logical)
        if self.flip:
            img = cv2.flip(img, {"h": 1, "v": 0, "hv": -1}[self.flip])
        if self.mono:
            img = cv2.cvtColor(img, cv2.COLOR_BGR2GRAY)
        self._delivered += 1
        return Frame(self.name, self.stamp_of(logical), img, seq=logical)

    def _pace(self, logical: int) -> None:
        now = time.monotonic()
        if self._t0 is None:
            self._t0 = now - logical / self.fps
        wait = self._t0 + logical / self.fps - now
        if wait > 0:
            time.sleep(wait)

    def stats(self) -> dict[str, int | float]:
        return {"frames": self._delivered, "fps": self.fps, "loops": self._loops}


def open_videos(paths: list[str | Path], names: list[str] | None = None, offsets: dict[str, int] | None = None,
                **kwargs) -> list[VideoFrameSource]:
    """One VideoFrameSource per file (names default to the file stems), not yet opened."""
    names = names or [Path(p).stem for p in paths]
    if len(names) != len(paths):
        raise SourceError(f"{len(paths)} videos but {len(names)} camera names")
    offsets = offsets or {}
    unknown = sorted(set(offsets) - set(names))
    if unknown:
        raise SourceError(f"frame offsets for unknown cameras {unknown} (cameras: {names})")
    return [VideoFrameSource(p, n, offset_frames=offsets.get(n, 0), **kwargs) for p, n in zip(paths, names)]


def to_bgr(image: np.ndarray) -> np.ndarray:
    return image if image.ndim == 3 else cv2.cvtColor(image, cv2.COLOR_GRAY2BGR)
