"""Accuracy and smoothness metrics (the paper's Table I: MPJPE and 3D-PCK per body group)."""

from __future__ import annotations

import numpy as np

from ..keypoints import GROUPS, INDEX

PCK_THRESHOLDS_MM = (50, 100, 150)


def joint_errors(pred: np.ndarray, gt: np.ndarray) -> np.ndarray:
    """Euclidean errors (T, J) in metres; NaN where either side is missing."""
    return np.linalg.norm(np.asarray(pred) - np.asarray(gt), axis=-1)


def summarize(errors: np.ndarray, keypoints: np.ndarray | None = None) -> dict[str, float | None]:
    """MPJPE (mm) and PCK (%) at 50/100/150 mm over finite entries of errors (T, J)."""
    e = errors if keypoints is None else errors[:, keypoints]
    e = e[np.isfinite(e)]
    if e.size == 0:
        return {"mpjpe_mm": None, **{f"pck{t}": None for t in PCK_THRESHOLDS_MM}, "n": 0}
    out: dict[str, float | None] = {"mpjpe_mm": float(e.mean() * 1000.0)}
    for t in PCK_THRESHOLDS_MM:
        out[f"pck{t}"] = float((e <= t / 1000.0).mean() * 100.0)
    out["n"] = int(e.size)
    return out


def table_one(pred: np.ndarray, gt: np.ndarray, scored: np.ndarray) -> dict[str, object]:
    """Total and per-group figures over the keypoints `scored` (bool (25,)): Head, UpperBody,
    LowerBody as in the paper's Table I. A group with no scored keypoint is None."""
    err = joint_errors(pred, gt)
    err[:, ~scored] = np.nan
    total = summarize(err)
    groups: dict[str, object] = {}
    for g, names in GROUPS.items():
        idx = np.array([INDEX[n] for n in names])
        idx = idx[scored[idx]]
        groups[g] = summarize(err, idx) if idx.size else None
    return {**total, "groups": groups}


def bone_length_std(keypoints: np.ndarray, bones: dict[str, tuple[str, str]]) -> float:
    """Largest standard deviation over time of any bone's length (m) in (T, 25, 3)."""
    worst = 0.0
    for a, b in bones.values():
        d = np.linalg.norm(keypoints[:, INDEX[a]] - keypoints[:, INDEX[b]], axis=-1)
        d = d[np.isfinite(d)]
        if d.size > 1:
            worst = max(worst, float(d.std()))
    return worst


def _acceleration(keypoints: np.ndarray, fps: float) -> np.ndarray:
    """Second finite difference (T-2, J, 3) in m/s^2."""
    return (keypoints[2:] - 2 * keypoints[1:-1] + keypoints[:-2]) * fps * fps


def jitter(keypoints: np.ndarray, fps: float, scored: np.ndarray | None = None) -> float:
    """Mean magnitude of the second finite difference (joint acceleration, m/s^2)."""
    p = keypoints if scored is None else keypoints[:, scored]
    a = np.linalg.norm(_acceleration(p, fps), axis=-1)
    a = a[np.isfinite(a)]
    return float(a.mean()) if a.size else float("nan")


def acceleration_error(keypoints: np.ndarray, truth: np.ndarray, fps: float, scored: np.ndarray | None = None) -> float:
    """Mean magnitude (m/s^2) of the joint acceleration's error against the truth's, both by
    second finite differences: what an acceleration analysis of the output gets wrong (jitter
    alone counts the motion's own acceleration too). Where three frames in a row are known."""
    if scored is not None:
        keypoints, truth = keypoints[:, scored], truth[:, scored]
    e = np.linalg.norm(_acceleration(keypoints, fps) - _acceleration(truth, fps), axis=-1)
    e = e[np.isfinite(e)]
    return float(e.mean()) if e.size else float("nan")
