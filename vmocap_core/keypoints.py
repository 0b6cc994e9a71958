"""The keypoint vocabulary of vmocap's skeleton, and the groups the paper's Table I scores.

Every PCM model, motion file and benchmark names keypoints with these strings. A model
that has only some of them leaves the rest unobserved (weight 0 in the IK).
"""

from __future__ import annotations

import numpy as np

# Order matters: arrays of keypoints (J, ...) follow this order.
KEYPOINTS: tuple[str, ...] = (
    "pelvis",
    "neck",
    "nose",
    "left_eye",
    "right_eye",
    "left_ear",
    "right_ear",
    "left_shoulder",
    "right_shoulder",
    "left_elbow",
    "right_elbow",
    "left_wrist",
    "right_wrist",
    "left_hand",
    "right_hand",
    "left_hip",
    "right_hip",
    "left_knee",
    "right_knee",
    "left_ankle",
    "right_ankle",
    "left_heel",
    "right_heel",
    "left_toe",
    "right_toe",
)
INDEX: dict[str, int] = {name: i for i, name in enumerate(KEYPOINTS)}

# Table I groups of the paper (Head, UpperBody, LowerBody); Total is all scored keypoints.
GROUPS: dict[str, tuple[str, ...]] = {
    "head": ("nose", "left_eye", "right_eye", "left_ear", "right_ear"),
    "upper_body": (
        "neck",
        "left_shoulder",
        "right_shoulder",
        "left_elbow",
        "right_elbow",
        "left_wrist",
        "right_wrist",
    ),
    "lower_body": (
        "pelvis",
        "left_hip",
        "right_hip",
        "left_knee",
        "right_knee",
        "left_ankle",
        "right_ankle",
    ),
}

# Lower-body keypoints are the ones the paper feeds from the rotated input image (III-B).
LOWER_BODY: tuple[str, ...] = GROUPS["lower_body"] + ("left_heel", "right_heel", "left_toe", "right_toe")


def indices(names: tuple[str, ...] | list[str]) -> np.ndarray:
    """Indices of `names` in KEYPOINTS (KeyError for an unknown name)."""
    return np.array([INDEX[n] for n in names], dtype=np.intp)


def mirror(name: str) -> str:
    """The left/right counterpart of a keypoint name (itself when it has none)."""
    if name.startswith("left_"):
        return "right_" + name[5:]
    if name.startswith("right_"):
        return "left_" + name[6:]
    return name


MIRROR: np.ndarray = indices([mirror(n) for n in KEYPOINTS])
