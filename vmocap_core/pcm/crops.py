"""Rotated square crops: where each PCM view looks in its camera image, and the exact affines.

A crop is (centre (2,) image px, side (image px), rotation (rad)) and is sampled into an N x N
network input. Rotation convention (the same as MediaPipe's rect rotation and as
`vmocap_core.method.rotation.trunk_tilt`): the crop's "up" direction points along the image vector
(sin r, -cos r), i.e. r = 0 is an upright crop and r > 0 means the person leans towards image
+u (clockwise on screen); the crop undoes it so the person reaches the CNN upright.

Pixel convention: OpenCV, pixel centres at integers in both the image and the crop. The crop
pixel p maps to the image point  c + s * R(r) @ (p - (N - 1) / 2),  s = side / N,  so the crop's
N pixels exactly tile the side (cv2.warpAffine with `image_to_crop` samples it).
"""

from __future__ import annotations

import warnings
from dataclasses import dataclass
from typing import Sequence

import numpy as np

from ..cameras.projection import Rig
from ..errors import ModelError
from ..keypoints import INDEX, KEYPOINTS
from ..method.rotation import trunk_lean

MIN_SIDE_PX = 32.0  # a crop smaller than this says nothing useful (and guards division by 0)


@dataclass
class Crops:
    """V crop rectangles; `camera` says which image each one is cut from."""

    camera: np.ndarray  # (V,) int
    center: np.ndarray  # (V, 2) image pixels
    side: np.ndarray  # (V,) image pixels
    rotation: np.ndarray  # (V,) radians, see module docstring
    valid: np.ndarray | None = None  # (V, len(KEYPOINTS)) bool: keypoints this view speaks for

    def __post_init__(self) -> None:
        self.camera = np.asarray(self.camera, dtype=np.intp).reshape(-1)
        V = self.camera.size
        self.center = np.asarray(self.center, dtype=np.float64).reshape(V, 2)
        self.side = np.asarray(self.side, dtype=np.float64).reshape(V)
        self.rotation = np.asarray(self.rotation, dtype=np.float64).reshape(V)
        if self.valid is None:
            self.valid = np.ones((V, len(KEYPOINTS)), dtype=bool)
        self.valid = np.asarray(self.valid, dtype=bool).reshape(V, len(KEYPOINTS))
        if not (np.isfinite(self.center).all() and np.isfinite(self.side).all() and np.isfinite(self.rotation).all()):
            raise ModelError("crop parameters must be finite")
        if (self.side <= 0).any():
            raise ModelError(f"crop sides must be positive, got {self.side}")

    def __len__(self) -> int:
        return self.camera.size

    @classmethod
    def from_rectangles(cls, cameras: Sequence[int], rects: Sequence[tuple[np.ndarray, float, float]]) -> "Crops":
        """Crops of (centre (2,), side, rotation) rectangles, one per camera in `cameras`
        (detector.Detection.crop's, rotated already)."""
        return cls(list(cameras), [r[0] for r in rects] or np.zeros((0, 2)), [r[1] for r in rects],
                   [r[2] for r in rects])

    def select(self, keep: np.ndarray) -> "Crops":
        """The crops where `keep` (V,) is True."""
        keep = np.asarray(keep, dtype=bool).reshape(len(self))
        assert self.valid is not None  # set by __post_init__
        return Crops(self.camera[keep], self.center[keep], self.side[keep], self.rotation[keep], self.valid[keep])

    def image_to_crop(self, n: int) -> np.ndarray:
        """(V, 2, 3) affines image pixel -> pixel of the n x n crop (see module docstring)."""
        return crop_affine(self.center, self.side, self.rotation, n)


def crop_affine(center: np.ndarray, side: np.ndarray, rotation: np.ndarray, n: int) -> np.ndarray:
    """(V, 2, 3) image -> crop affines:  p = (n - 1) / 2 + R(r)^T (u - c) / s,  s = side / n."""
    center = np.asarray(center, dtype=np.float64).reshape(-1, 2)
    side = np.asarray(side, dtype=np.float64).reshape(-1)
    rot = np.asarray(rotation, dtype=np.float64).reshape(-1)
    inv_s = n / side
    c, s = np.cos(rot), np.sin(rot)
    M = np.empty((rot.size, 2, 2))
    M[:, 0, 0], M[:, 0, 1] = c * inv_s, s * inv_s  # R^T / s
    M[:, 1, 0], M[:, 1, 1] = -s * inv_s, c * inv_s
    t = (n - 1) / 2.0 - np.einsum("vij,vj->vi", M, center)
    return np.concatenate([M, t[:, :, None]], axis=2)


def compose_affine(A: np.ndarray, B: np.ndarray) -> np.ndarray:
    """(..., 2, 3) affine of x -> A(B(x))."""
    M = A[..., :2, :2] @ B[..., :2, :2]
    t = np.einsum("...ij,...j->...i", A[..., :2, :2], B[..., :2, 2]) + A[..., :2, 2]
    return np.concatenate([M, t[..., None]], axis=-1)


def tilt_from_points(bottom: np.ndarray, top: np.ndarray) -> np.ndarray:
    """Rotation (...,) that makes the image vector bottom -> top point up in the crop."""
    d = np.asarray(top, dtype=np.float64) - np.asarray(bottom, dtype=np.float64)
    return np.arctan2(d[..., 0], -d[..., 1])


def crops_from_keypoints_2d(
    uv: np.ndarray, rotation: np.ndarray | None = None, margin: float = 1.25, min_side: float = MIN_SIDE_PX
) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """Square crops around 2D keypoints (C, 25, 2) in KEYPOINTS order (NaN = unknown).

    The box is the keypoints' extent measured in the crop's rotated frame, centred on the
    middle of that extent, side = longer extent * `margin` (MediaPipe's ROI uses 1.25 too).
    rotation: (C,) radians; default the projected pelvis -> neck tilt (0 where unknown).
    Returns centre (C, 2), side (C,), rotation (C,); cameras without two finite keypoints
    get side NaN (no crop possible).
    """
    uv = np.asarray(uv, dtype=np.float64)
    if rotation is None:
        rot = tilt_from_points(uv[:, INDEX["pelvis"]], uv[:, INDEX["neck"]])
    else:
        rot = np.asarray(rotation, dtype=np.float64).reshape(uv.shape[0])
    rot = np.where(np.isfinite(rot), rot, 0.0)  # unknown tilt (trunk not visible): upright
    c, s = np.cos(rot), np.sin(rot)
    # coordinates in the crop frame (x along (c, s), y along (-s, c)), rotation about the origin
    x = uv[..., 0] * c[:, None] + uv[..., 1] * s[:, None]
    y = -uv[..., 0] * s[:, None] + uv[..., 1] * c[:, None]
    ok = np.isfinite(x) & np.isfinite(y)
    enough = ok.sum(axis=1) >= 2
    xm = np.where(ok, x, np.nan)
    ym = np.where(ok, y, np.nan)
    with warnings.catch_warnings():  # cameras that see no keypoint: all-NaN rows, handled below
        warnings.simplefilter("ignore", RuntimeWarning)
        x0, x1 = np.nanmin(xm, axis=1), np.nanmax(xm, axis=1)
        y0, y1 = np.nanmin(ym, axis=1), np.nanmax(ym, axis=1)
    cx, cy = (x0 + x1) / 2, (y0 + y1) / 2
    center = np.stack([cx * c - cy * s, cx * s + cy * c], axis=1)
    side = np.maximum(np.maximum(x1 - x0, y1 - y0) * margin, min_side)
    side = np.where(enough, side, np.nan)
    return center, side, rot


# Least crop side / (margin x body_length at the pelvis' depth): below the extent of a person
# upright in the view (whose crops stay as they were: tight crops gave the demo's real videos
# their best reprojection), above that of a body foreshortened in the view.
BODY_FRACTION = 0.8
# The same for a body that is not standing: above an upright person's extent, so that a body
# lying, rolling, crouching or getting up keeps the scale BlazePose was trained at (with
# BODY_FRACTION the CNN lost such bodies, docs/benchmarks.md "Session 35"). Reached, linearly,
# when the trunk leans TURNED_LEAN[1] or more from the world's up (z), or when the body's height
# along z (head, trunk and legs: the arms say nothing of the stance) is COMPACT_HEIGHT[0] x
# body_length or less; whichever is further along. People bending over with their legs under
# them keep BODY_FRACTION (the demo's subject: trunk lean up to 43 degrees, height 0.76-0.90).
# Several people tracked at once keep BODY_FRACTION: a larger crop takes in the person beside.
TURNED_BODY_FRACTION = 1.1
TURNED_LEAN = (np.radians(45.0), np.radians(90.0))
COMPACT_HEIGHT = (0.45, 0.7)
_STANCE = [INDEX[k] for k in ("nose", "neck", "pelvis", "left_hip", "right_hip", "left_knee", "right_knee",
                              "left_ankle", "right_ankle")]


def body_length(keypoints: np.ndarray) -> float:
    """A pose-independent length of a skeleton (25, 3): mean leg (hip-knee-ankle) + pelvis-neck +
    neck-nose, metres (NaN when a part is missing)."""
    kp = np.asarray(keypoints, dtype=np.float64)

    def d(a: str, b: str) -> float:
        return float(np.linalg.norm(kp[INDEX[a]] - kp[INDEX[b]]))

    leg = np.nanmean([d(f"{s}_hip", f"{s}_knee") + d(f"{s}_knee", f"{s}_ankle") for s in ("left", "right")])
    return float(leg + d("pelvis", "neck") + d("neck", "nose"))


def stance_height(keypoints: np.ndarray, length: float | None = None) -> float:
    """The extent along the world's up (z) of a skeleton's (25, 3) head, trunk and legs over its
    body_length (`length`, when the caller has it): about 0.9 standing, below 0.5 sitting,
    crouching or lying (NaN when unknown)."""
    kp = np.asarray(keypoints, dtype=np.float64)
    z = kp[_STANCE, 2]
    z = z[np.isfinite(z)]
    size = body_length(kp) if length is None else length
    return float((z.max() - z.min()) / size) if z.size >= 2 else float("nan")


def _ramp(x: float, start: float, full: float) -> float:
    """0 at `start`, 1 at `full` (either order), linear between, clipped; 0 where x is unknown."""
    return float(np.nan_to_num(np.clip((x - start) / (full - start), 0.0, 1.0)))


def crops_from_skeleton(
    rig: Rig,
    keypoints: np.ndarray,
    rotation: np.ndarray | None = None,
    margin: float = 1.25,
    turned_fraction: float = TURNED_BODY_FRACTION,
) -> tuple[np.ndarray, np.ndarray, np.ndarray, np.ndarray]:
    """Crops for every camera from the current 3D skeleton (25, 3) in KEYPOINTS order (metres).

    Projects with `rig.project` (lens distortion included); points behind a camera are ignored.
    rotation: (C,) per-camera trunk tilt (e.g. `tracker.trunk_tilt(rig, keypoints)`); default
    computed here from the projected pelvis -> neck vector; pass zeros for upright crops.
    The side is at least BODY_FRACTION (up to `turned_fraction` for a body lying, crouching or
    turned over) x margin x body_length imaged at the pelvis' depth.
    Returns centre (C, 2), side (C,), rotation (C,), usable (C,) bool (False: the body is not
    in front of the camera or its crop lies entirely outside the image).
    """
    kp = np.asarray(keypoints, dtype=np.float64)
    if kp.shape != (len(KEYPOINTS), 3):
        raise ModelError(f"keypoints must be ({len(KEYPOINTS)}, 3), got {kp.shape}")
    uv, front = rig.project(kp)  # (C, 25, 2), (C, 25)
    uv = np.where(front[..., None] & np.isfinite(kp).all(axis=1)[None, :, None], uv, np.nan)  # type: ignore[index]  # numpy stub: all(axis=1) is an array
    center, side, rot = crops_from_keypoints_2d(uv, rotation, margin)
    # The 2D extent shrinks with the pose (lying along a camera's line of sight, crouching), but
    # BlazePose expects the person at a pose-independent scale (MediaPipe's crop: 2.5 x hips to
    # head-top): a crop fitted to a foreshortened body was half the detector's, and the hips came
    # out 20-70 px off with presence ~0. So the side is at least a fraction of `margin` x the
    # body's length (legs + trunk + neck to nose, pose-independent) imaged at the pelvis' depth.
    size = body_length(kp)
    depth = rig.to_camera_frames(kp[INDEX["pelvis"]][None])[:, 0, 2]  # (C,)
    focal = np.array([c.K[0, 0] for c in rig.cameras])
    # how far from standing the body is, the same in every view (a camera mounted rolled sees an
    # upright body upside down: its crop stays an upright body's)
    turn = max(_ramp(float(trunk_lean(kp)), *TURNED_LEAN), _ramp(stance_height(kp, size), COMPACT_HEIGHT[1], COMPACT_HEIGHT[0]))
    fraction = BODY_FRACTION + (turned_fraction - BODY_FRACTION) * turn
    with np.errstate(divide="ignore", invalid="ignore"):
        least = np.where((depth > 0) & np.isfinite(size), fraction * margin * size * focal / depth, 0.0)
    side = np.where(np.isfinite(side), np.maximum(side, least), side)
    wh = np.array([[c.width, c.height] for c in rig.cameras], dtype=np.float64)
    half = np.where(np.isfinite(side), side, 0.0)[:, None] * 0.7072  # circumradius of the square
    overlaps = np.all((center + half > 0) & (center - half < wh), axis=1)
    usable = np.isfinite(side) & overlaps
    center = np.where(usable[:, None], center, 0.0)
    return center, np.where(usable, side, MIN_SIDE_PX), rot, usable
