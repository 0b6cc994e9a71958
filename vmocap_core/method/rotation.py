"""Image rotation by the trunk tilt (paper III-B): inverted bodies made upright for the CNN."""

from __future__ import annotations

import numpy as np

from ..cameras.projection import Rig
from ..keypoints import INDEX


def trunk_tilt(rig: Rig, keypoints: np.ndarray) -> np.ndarray:
    """Per camera, the angle (radians, in (-pi, pi]) of the projected pelvis->neck vector from
    image-up: 0 upright, pi upside down. Rotating the input image by this angle makes the person
    upright for the CNN (paper III-B)."""
    pts = np.asarray(keypoints)[[INDEX["pelvis"], INDEX["neck"]]]
    uv, _ = rig.project(pts)  # (C, 2, 2)
    d = uv[:, 1] - uv[:, 0]
    return np.arctan2(d[:, 0], -d[:, 1])


def trunk_lean(keypoints: np.ndarray) -> np.ndarray:
    """The angle (radians, (...,)) of the pelvis->neck vector from the world's up (z) for
    keypoints (..., 25, 3): 0 upright, pi upside down; NaN where the trunk is unknown."""
    kp = np.asarray(keypoints, dtype=np.float64)
    trunk = kp[..., INDEX["neck"], :] - kp[..., INDEX["pelvis"], :]
    with np.errstate(divide="ignore", invalid="ignore"):
        return np.arccos(np.clip(trunk[..., 2] / np.linalg.norm(trunk, axis=-1), -1.0, 1.0))
