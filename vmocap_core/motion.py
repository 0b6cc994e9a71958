"""Motion clips: 3D keypoint ground truth (.npz: joints (T, J, 3) metres Z up, names (J,), fps)."""

from __future__ import annotations

from dataclasses import dataclass
from pathlib import Path

import numpy as np

from .errors import MotionFileError
from .keypoints import INDEX, KEYPOINTS


@dataclass
class Motion:
    name: str
    positions: np.ndarray  # (T, 25, 3) in KEYPOINTS order, NaN for keypoints the clip lacks
    present: np.ndarray  # (25,) bool
    fps: float

    @property
    def n_frames(self) -> int:
        return self.positions.shape[0]

    def is_inverted(self) -> bool:
        """The neck below both ankles in any frame (the issue's definition)."""
        need = [INDEX[n] for n in ("neck", "left_ankle", "right_ankle")]
        if not self.present[need].all():
            return False
        z = self.positions[:, need, 2]
        return bool(np.any((z[:, 0] < z[:, 1]) & (z[:, 0] < z[:, 2])))


def _read_clip(path: Path) -> tuple[np.ndarray, list[str], float]:
    """A clip file's joints (T, J, 3), their names and fps, as stored (MotionFileError if it is none)."""
    try:
        with np.load(path, allow_pickle=False) as d:
            joints = np.asarray(d["joints"], dtype=np.float64)
            names = [str(n) for n in d["names"]]
            fps = float(d["fps"])
    except (OSError, ValueError, KeyError) as exc:
        raise MotionFileError(f"{path}: not a motion clip ({exc})") from None
    if joints.ndim != 3 or joints.shape[2] != 3 or joints.shape[1] != len(names) or joints.shape[0] < 2:
        raise MotionFileError(f"{path}: joints must be (T>=2, J, 3) with J names, got {joints.shape} and {len(names)} names")
    if not np.isfinite(fps) or fps <= 0:
        raise MotionFileError(f"{path}: fps must be positive, got {fps}")
    if not any(n in INDEX for n in names):
        raise MotionFileError(f"{path}: none of the keypoint names {names} is in the vocabulary")
    return joints, names, fps


def load_motion(path: str | Path) -> Motion:
    """Read a motion clip; keypoint names outside the vocabulary are ignored."""
    path = Path(path)
    joints, names, fps = _read_clip(path)
    pos = np.full((joints.shape[0], len(KEYPOINTS), 3), np.nan)
    present = np.zeros(len(KEYPOINTS), dtype=bool)
    for j, n in enumerate(names):
        if n in INDEX:
            pos[:, INDEX[n]] = joints[:, j]
            present[INDEX[n]] = True
    return Motion(path.stem, pos, present, fps)


def resample(motion: Motion, fps: float) -> Motion:
    """Linear interpolation to a new frame rate."""
    T = motion.n_frames
    duration = (T - 1) / motion.fps
    n = int(np.floor(duration * fps)) + 1
    t_new = np.arange(n) / fps
    t_old = np.arange(T) / motion.fps
    flat = motion.positions.reshape(T, -1)
    out = np.empty((n, flat.shape[1]))
    for i in range(flat.shape[1]):  # per channel, once per clip (offline)
        out[:, i] = np.interp(t_new, t_old, flat[:, i])
    return Motion(motion.name, out.reshape(n, *motion.positions.shape[1:]), motion.present, fps)


def extend(motion: Motion, min_seconds: float) -> Motion:
    """Play forward, backward, forward ... until at least `min_seconds` long."""
    seq = [motion.positions]
    fwd = False
    while sum(len(s) for s in seq) / motion.fps < min_seconds:
        seq.append((motion.positions if fwd else motion.positions[::-1])[1:])
        fwd = not fwd
    return Motion(motion.name, np.concatenate(seq), motion.present, motion.fps)


TRANSFORMS = ("reversed", "mirrored")  # motions made from a clip (`transformed`)


def _mirrored_names(names: list[str]) -> list[int]:
    """Per keypoint name, the index of its left/right counterpart (itself for the midline)."""
    def other(n: str) -> str:
        if n.startswith("left_"):
            return "right_" + n[len("left_"):]
        if n.startswith("right_"):
            return "left_" + n[len("right_"):]
        return n
    return [names.index(other(n)) if other(n) in names else i for i, n in enumerate(names)]


def transformed(path: str | Path, kind: str, folder: str | Path) -> Path:
    """A motion made from the clip at `path`, written to `folder` as STEM_KIND.npz: `reversed`
    (played backwards: getting up becomes lying down, a roll rolls the other way, a backflip's
    rotation turns round) or `mirrored` (reflected in the clip's x-z plane, left and right
    swapped: a cartwheel to the other side). Physically the body's motions are as plausible;
    the tracker has seen neither."""
    if kind not in TRANSFORMS:
        raise MotionFileError(f"unknown transform {kind!r} (known: {', '.join(TRANSFORMS)})")
    joints, names, fps = _read_clip(Path(path))
    if kind == "reversed":
        joints = joints[::-1]
    else:
        joints = joints[:, _mirrored_names(names)] * np.array([1.0, -1.0, 1.0])
    out = Path(folder) / f"{Path(path).stem}_{kind}.npz"
    out.parent.mkdir(parents=True, exist_ok=True)
    np.savez(out, joints=np.ascontiguousarray(joints), names=np.array(names), fps=np.array(fps))
    return out
