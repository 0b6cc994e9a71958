"""Why a subject is not initialized: the views' disagreement, in words a user can act on.

Initialization (II-C) needs the core keypoints triangulated from views that agree (residual at
most `init_max_reprojection_px`) on `init_frames` consecutive frame sets (with an identification
phase after it, a limb keypoint on most of them and the last). When it stalls, the cause is
almost always visible in the triangulation: a keypoint whose views disagree by tens
of pixels (wrong calibration, a wrong CNN, two people), a keypoint seen by fewer than two
cameras, or cameras that contribute nothing at all (no person in view, or a CNN presence below
`min_presence`).
"""

from __future__ import annotations

from typing import Any, Sequence

import numpy as np

from ..keypoints import INDEX

# Keypoints that must be seen to identify a body (II-C).
CORE = ("left_shoulder", "right_shoulder", "left_elbow", "right_elbow", "left_wrist", "right_wrist",
        "left_hip", "right_hip", "left_knee", "right_knee", "left_ankle", "right_ankle")
MAX_LISTED = 4  # keypoints named per cause; the rest are counted


def camera_mask(weights: np.ndarray) -> np.ndarray:
    """(J,) bit masks of the cameras with weight > 0 per keypoint, from (C, J) weights."""
    w = np.asarray(weights) > 0
    bits = np.left_shift(np.uint64(1), np.arange(w.shape[0], dtype=np.uint64))
    return (w.astype(np.uint64) * bits[:, None]).sum(axis=0).astype(np.uint32)


def _names(items: list[str]) -> str:
    more = len(items) - MAX_LISTED
    return ", ".join(items[:MAX_LISTED]) + (f" and {more} more" if more > 0 else "")


def describe(residual_px: np.ndarray, cameras: np.ndarray, camera_names: Sequence[str], bound_px: float,
             presence: dict[str, float] | None = None, min_presence: float | None = None) -> str:
    """One line: which core keypoints fail and why, and which cameras give nothing.

    residual_px (25,): triangulation residual (NaN: not triangulated); cameras (25,): bit masks
    of the cameras seeing each keypoint; presence: CNN presence per camera, where known."""
    residual_px = np.asarray(residual_px, dtype=np.float64)
    cameras = np.asarray(cameras, dtype=np.uint64)
    n_cams = np.array([bin(int(m)).count("1") for m in cameras])
    disagree, unseen = [], []
    for name in CORE:
        j = INDEX[name]
        if n_cams[j] < 2:
            unseen.append(f"{name} ({n_cams[j]} camera{'s' if n_cams[j] != 1 else ''})")
        elif not residual_px[j] <= bound_px:
            disagree.append(f"{name} {residual_px[j]:.1f} px" if np.isfinite(residual_px[j]) else name)
    parts = []
    if disagree:
        parts.append(f"views disagree on {_names(disagree)} (bound {bound_px:g} px)")
    if unseen:
        parts.append(f"seen by fewer than 2 cameras: {_names(unseen)}")
    used = int(np.bitwise_or.reduce(cameras)) if cameras.size else 0
    silent = [n for c, n in enumerate(camera_names) if not used >> c & 1]
    if silent:
        if presence is not None:
            silent = [f"{n} (presence {presence[n]:.2f})" if n in presence else f"{n} (no view)" for n in silent]
        limit = f", min_presence {min_presence:g}" if min_presence is not None else ""
        parts.append(f"no keypoint from {_names(silent)} (no person found or low CNN presence{limit})")
    if not parts:
        return "the core keypoints agree; waiting for enough consecutive frame sets or a skeleton fit"
    return "; ".join(parts)


def not_initialized_reason(markers: Any, camera_names: Sequence[str], bound_px: float, problem: str | None = None,
                           min_presence: float | None = None) -> str:
    """Why no subject is initialized, from a frame set's virtual markers (results.Markers):
    no heatmap views at all, else the skeleton fit's `problem` when one failed, else `describe`."""
    if markers.kind == "none":
        return "no heatmap views (no frames, or the CNN found nobody)"
    return problem or describe(markers.residual_px, markers.cameras, camera_names, bound_px, markers.presence, min_presence)

