"""Readers of the Shelf benchmark files (format: ../shared/data/shelf/README.md).

- detection/<camera>.txt: per frame the OpenPose BODY_25 joint candidates of one view and the
  part-affinity scores between candidates of the 26 BODY_25 limbs.
- gt.txt: per frame the ground-truth people (Shelf-15 joints, metres).

Both readers are line oriented so an error names the file and the line; blank lines carry no
information in these files (an empty Eigen row prints as one) and are skipped.
"""

from __future__ import annotations

from dataclasses import dataclass, field
from pathlib import Path
from typing import Iterator

import numpy as np

from ...cameras.projection import Rig
from ...errors import DetectionFileError
from ...keypoints import INDEX

BODY25_NAMES: tuple[str, ...] = (
    "nose", "neck", "r_shoulder", "r_elbow", "r_wrist", "l_shoulder", "l_elbow", "l_wrist",
    "mid_hip", "r_hip", "r_knee", "r_ankle", "l_hip", "l_knee", "l_ankle", "r_eye", "l_eye",
    "r_ear", "l_ear", "l_big_toe", "l_small_toe", "l_heel", "r_big_toe", "r_small_toe", "r_heel",
)
N_BODY25 = 25
# OpenPose BODY_25 pair list, in the order the PAF matrices are written.
BODY25_LIMBS: tuple[tuple[int, int], ...] = (
    (1, 8), (9, 10), (10, 11), (8, 9), (8, 12), (12, 13), (13, 14), (1, 2), (2, 3), (3, 4),
    (2, 17), (1, 5), (5, 6), (6, 7), (5, 18), (1, 0), (0, 15), (0, 16), (15, 17), (16, 18),
    (14, 19), (19, 20), (14, 21), (11, 22), (22, 23), (11, 24),
)
SKEL_BODY25 = 4

# BODY_25 joint -> our keypoint vocabulary (small toes have no counterpart; hands are absent).
_TO_OURS = {
    "nose": "nose", "neck": "neck", "r_shoulder": "right_shoulder", "r_elbow": "right_elbow",
    "r_wrist": "right_wrist", "l_shoulder": "left_shoulder", "l_elbow": "left_elbow",
    "l_wrist": "left_wrist", "mid_hip": "pelvis", "r_hip": "right_hip", "r_knee": "right_knee",
    "r_ankle": "right_ankle", "l_hip": "left_hip", "l_knee": "left_knee", "l_ankle": "left_ankle",
    "r_eye": "right_eye", "l_eye": "left_eye", "r_ear": "right_ear", "l_ear": "left_ear",
    "l_big_toe": "left_toe", "r_big_toe": "right_toe", "l_heel": "left_heel", "r_heel": "right_heel",
}
# (25,) index into KEYPOINTS of each BODY_25 joint, -1 where we have no such keypoint.
BODY25_TO_KEYPOINT = np.array([INDEX[_TO_OURS[n]] if n in _TO_OURS else -1 for n in BODY25_NAMES], dtype=np.intp)

# Shelf-15 ground-truth joint order.
SHELF15_NAMES: tuple[str, ...] = (
    "r_ankle", "r_knee", "r_hip", "l_hip", "l_knee", "l_ankle", "r_wrist", "r_elbow",
    "r_shoulder", "l_shoulder", "l_elbow", "l_wrist", "head_bottom", "head_top", "pelvis",
)


@dataclass
class ViewFrame:
    """The OpenPose output of one view in one frame."""

    candidates: list[np.ndarray]  # per BODY_25 joint an (n, 3) array: x px, y px, score
    paf: list[np.ndarray]  # per limb an (nA, nB) score matrix (empty when a side has none)


@dataclass
class GtFrame:
    ids: np.ndarray  # (P,) int
    joints: np.ndarray  # (P, 15, 3) metres
    valid: np.ndarray  # (P, 15) bool


class _Lines:
    """Non-blank lines of a text file with their 1-based line numbers."""

    def __init__(self, path: Path) -> None:
        self.path = path
        try:
            text = path.read_text()
        except OSError as exc:
            raise DetectionFileError(f"{path}: cannot read ({exc})") from None
        self._lines = [(i + 1, ln) for i, ln in enumerate(text.splitlines()) if ln.strip()]
        self._pos = 0
        self.last_line = len(text.splitlines())

    def next(self, what: str) -> tuple[int, list[str]]:
        if self._pos >= len(self._lines):
            raise DetectionFileError(f"{self.path}: line {self.last_line + 1}: file ends where {what} was expected")
        lineno, text = self._lines[self._pos]
        self._pos += 1
        return lineno, text.split()

    def ints(self, what: str, count: int) -> tuple[int, list[int]]:
        lineno, tok = self.next(what)
        if len(tok) != count:
            raise DetectionFileError(f"{self.path}: line {lineno}: expected {what} ({count} integer(s)), got {len(tok)} value(s)")
        try:
            return lineno, [int(t) for t in tok]
        except ValueError:
            raise DetectionFileError(f"{self.path}: line {lineno}: expected {what} (integers), got {' '.join(tok)!r}") from None

    def floats(self, what: str, count: int) -> np.ndarray:
        lineno, tok = self.next(what)
        if len(tok) != count:
            raise DetectionFileError(
                f"{self.path}: line {lineno}: expected {count} numbers for {what}, got {len(tok)} (truncated line?)"
            )
        try:
            arr = np.array([float(t) for t in tok])
        except ValueError:
            raise DetectionFileError(f"{self.path}: line {lineno}: non-numeric value in {what}") from None
        if not np.all(np.isfinite(arr)):
            raise DetectionFileError(f"{self.path}: line {lineno}: NaN or infinite value in {what}")
        return arr

    def at_end(self) -> bool:
        return self._pos >= len(self._lines)

    def peek_line(self) -> int:
        return self._lines[self._pos][0] if self._pos < len(self._lines) else self.last_line + 1


def read_detections(path: str | Path, width: int, height: int, max_frames: int | None = None) -> list[ViewFrame]:
    """Parse one view's detection file. Pixel = normalised * (size - 1) (README).
    With `max_frames`, only the first frames are read (and the rest is not checked)."""
    path = Path(path)
    lines = _Lines(path)
    _, (skel, n_frames) = lines.ints("header 'skelType frameCount'", 2)
    if skel != SKEL_BODY25:
        raise DetectionFileError(f"{path}: line 1: skelType {skel} is not BODY_25 ({SKEL_BODY25})")
    frames: list[ViewFrame] = []
    for f in range(n_frames if max_frames is None else min(n_frames, max_frames)):
        cands: list[np.ndarray] = []
        for j in range(N_BODY25):
            what = f"frame {f} of {n_frames}: candidate count of joint {j} ({BODY25_NAMES[j]})"
            lineno, (n,) = lines.ints(what, 1)
            if n < 0:
                raise DetectionFileError(f"{path}: line {lineno}: negative candidate count {n}")
            if n == 0:
                cands.append(np.zeros((0, 3)))
                continue
            rows = [lines.floats(f"frame {f}: {axis} row of joint {j} ({BODY25_NAMES[j]})", n) for axis in ("x", "y", "score")]
            c = np.stack(rows, axis=1)
            c[:, 0] *= width - 1
            c[:, 1] *= height - 1
            cands.append(c)
        pafs: list[np.ndarray] = []
        for li, (a, b) in enumerate(BODY25_LIMBS):
            na, nb = len(cands[a]), len(cands[b])
            if na == 0 or nb == 0:
                pafs.append(np.zeros((na, nb)))
                continue
            pafs.append(np.stack([lines.floats(f"frame {f}: PAF row {r} of limb {li} {a}-{b}", nb) for r in range(na)]))
        frames.append(ViewFrame(cands, pafs))
    if max_frames is None and not lines.at_end():
        raise DetectionFileError(f"{path}: line {lines.peek_line()}: unexpected data after the {n_frames} frames of the header")
    return frames


def read_gt(path: str | Path) -> list[GtFrame]:
    """Parse gt.txt (Shelf-15 joints per person, metres)."""
    path = Path(path)
    lines = _Lines(path)
    _, (n_joints, n_frames) = lines.ints("header 'jointCount frameCount'", 2)
    out: list[GtFrame] = []
    for f in range(n_frames):
        _, (n_people,) = lines.ints(f"frame {f}: person count", 1)
        ids, joints, valid = [], [], []
        for _ in range(n_people):
            _, (pid,) = lines.ints(f"frame {f}: person id", 1)
            rows = [lines.floats(f"frame {f}: person {pid} row {r}", n_joints) for r in range(4)]
            ids.append(pid)
            joints.append(np.stack(rows[:3], axis=1))
            valid.append(rows[3] > 0)
        out.append(
            GtFrame(
                ids=np.array(ids, dtype=int),
                joints=np.array(joints, dtype=np.float64).reshape(-1, n_joints, 3),
                valid=np.array(valid, dtype=bool).reshape(-1, n_joints),
            )
        )
    if not lines.at_end():
        raise DetectionFileError(f"{path}: line {lines.peek_line()}: unexpected data after the {n_frames} frames of the header")
    return out


@dataclass
class ShelfData:
    rig: Rig
    views: list[list[ViewFrame]]  # [camera][frame]
    gt: list[GtFrame]
    names: list[str] = field(default_factory=list)

    @property
    def n_frames(self) -> int:
        return min(len(v) for v in self.views)


def load_shelf(root: str | Path, max_frames: int | None = None) -> ShelfData:
    from ...cameras.rig_file import load_shelf_calibration

    root = Path(root)
    rig = load_shelf_calibration(root / "calibration.json")
    views = [read_detections(root / "detection" / f"{cam.name}.txt", cam.width, cam.height, max_frames) for cam in rig]
    gt = read_gt(root / "gt.txt")
    n = min(min(len(v) for v in views), len(gt))
    if max_frames is not None:
        n = min(n, max_frames)
    return ShelfData(rig=rig, views=[v[:n] for v in views], gt=gt[:n], names=rig.names)


def iter_frames(data: ShelfData) -> Iterator[tuple[int, list[ViewFrame], GtFrame]]:
    for f in range(data.n_frames):
        yield f, [v[f] for v in data.views], data.gt[f]
