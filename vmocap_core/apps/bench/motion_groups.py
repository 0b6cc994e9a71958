"""Motion groups of the image benchmark, computed from the keypoints (not by clip name).

- floor: the pelvis is low (below LOW_PELVIS x leg length above the clip's lowest point) in at
  least FLOOR_SHARE of the frames: lying, rolling, crawling, getting up;
- inverted: otherwise, the trunk upside down (pelvis->neck more than UPSIDE_DOWN_DEG from
  vertical) in at least INVERTED_SHARE of the frames: cartwheel, backflip;
- regular: the rest (upright).

Floor comes first: a roll or a get-up turns the trunk over too, but near the ground, where the
CNN sees a lying body rather than a standing one upside down.
"""

from __future__ import annotations

import numpy as np

from ...errors import VmocapError
from ...keypoints import INDEX
from ...method.rotation import trunk_lean

GROUPS = ("regular", "inverted", "floor")
LOW_PELVIS = 0.6  # x leg length (hip-knee-ankle): a standing pelvis is at ~1.0, a kneeling one at ~0.5
FLOOR_SHARE = 0.25
UPSIDE_DOWN_DEG = 120.0
INVERTED_SHARE = 0.05


def group_features(positions: np.ndarray) -> dict[str, float]:
    """positions (T, 25, 3), Z up, NaN for keypoints a clip lacks: the share of frames with a
    low pelvis and with the trunk upside down, and the leg length (m)."""
    need = ("pelvis", "neck", "left_hip", "left_knee", "left_ankle", "right_hip", "right_knee", "right_ankle")
    P = {n: positions[:, INDEX[n]] for n in need}
    if not all(np.isfinite(p).all() for p in P.values()):
        raise VmocapError(f"grouping a motion needs every frame's {', '.join(need)}")
    legs = [np.linalg.norm(P[f"{s}_hip"] - P[f"{s}_knee"], axis=1) + np.linalg.norm(P[f"{s}_knee"] - P[f"{s}_ankle"], axis=1)
            for s in ("left", "right")]
    leg = float(np.median(np.concatenate(legs)))
    ground = float(np.nanmin(positions[..., 2]))
    tilt = np.degrees(trunk_lean(positions))
    return {"low_pelvis_share": float(np.mean(P["pelvis"][:, 2] - ground < LOW_PELVIS * leg)),
            "upside_down_share": float(np.mean(tilt > UPSIDE_DOWN_DEG)), "leg_m": leg}


def motion_group(positions: np.ndarray) -> str:
    """One of GROUPS for a motion's keypoints (T, 25, 3)."""
    f = group_features(positions)
    if f["low_pelvis_share"] >= FLOOR_SHARE:
        return "floor"
    if f["upside_down_share"] >= INVERTED_SHARE:
        return "inverted"
    return "regular"
