"""A view whose CNN drew the body's sides swapped: read its maps the other way round.

A landmark CNN that sees a crouched, turned or tumbling body from behind or below often draws
it mirrored: its left-wrist map peaks on the right wrist, and so on for a whole limb group, in
one or two cameras while the others draw it right. The lattice search (eq. 1) sums every view
at each lattice point, so a mirrored view adds nothing near the true keypoint (its peak lies
on the other side of the body) and the marker weakens; the search at the maps' peaks
(MarkerStage._reacquire) can then take the other side's peaks, triangulated from the mirrored
views, and fold the limb across the body.

So, before the search, each view is asked per group of paired keypoints (arms, legs, face):
are its maps higher at the predicted keypoints, or at the predicted keypoints of the other
side? A view that reads the group clearly higher the other way round has that group's left and
right channels swapped, for the lattice search, the re-acquisition, the refinement and the
consistency check of that frame set alike. At least two cameras must read the group as drawn,
and no fewer than would be swapped: when most views read the body mirrored, it is the prediction
that is mirrored (a tracker that swapped the sides), and the maps, as drawn, bring it back.
"""

from __future__ import annotations

import dataclasses

import numpy as np

from ..cameras.projection import Rig
from ..keypoints import KEYPOINTS, MIRROR
from ..pcm.views import PcmViews
from .lattice import PcmSampler

# the left/right pairs by limb group: a CNN swaps a whole arm or leg chain, not a single joint
_GROUPS = {
    "arms": ("shoulder", "elbow", "wrist", "hand"),
    "legs": ("hip", "knee", "ankle", "heel", "toe"),
    "face": ("eye", "ear"),
}
# (G, 25) bool: the sided keypoints of each group
GROUP_MASK = np.array([[n.startswith(("left_", "right_")) and n.split("_", 1)[1] in parts for n in KEYPOINTS]
                       for parts in _GROUPS.values()])


def swapped_groups(rig: Rig, pcm: PcmViews, predicted: np.ndarray, ratio: float, min_value: float,
                   sampler: PcmSampler | None = None) -> np.ndarray:
    """(V, G) bool: the views' limb groups whose maps read the predicted keypoints (25, 3)
    `ratio` times higher the other way round, and at least `min_value` summed over the group
    (module doc). A group is swapped only where at least two cameras, and no fewer than would
    swap, read it as drawn by the same margin."""
    kp = np.asarray(pcm.keypoints, dtype=np.intp)
    if pcm.n_views == 0:
        return np.zeros((0, GROUP_MASK.shape[0]), dtype=bool)
    pts = np.asarray(predicted, dtype=np.float64)
    known = np.isfinite(pts[kp]).all(axis=1) & np.isfinite(pts[MIRROR[kp]]).all(axis=1)
    sampler = sampler or PcmSampler(rig, pcm)
    # each channel j read at keypoint j (as drawn) and at its mirror keypoint (turned), in one pass
    both = np.where(known[:, None, None], np.stack([pts[kp], pts[MIRROR[kp]]], axis=1), 0.0)  # (J, 2, 3)
    values = sampler.point_values(both)  # (V, J, 2)
    as_drawn, turned = values[..., 0], values[..., 1]
    member = GROUP_MASK[:, kp] & known[None, :]  # (G, J)
    drawn = as_drawn @ member.T  # (V, G)
    other = turned @ member.T
    out = (other >= ratio * drawn) & (other >= min_value)
    confirm = (drawn >= ratio * other) & (drawn >= min_value)
    cam = np.asarray(pcm.camera, dtype=np.intp)
    for g in np.flatnonzero(out.any(axis=0)):  # a few groups: the cameras that would swap against those that confirm
        swapping = np.unique(cam[out[:, g]]).size
        if np.unique(cam[confirm[:, g]]).size < max(2, swapping):
            out[:, g] = False
    return out


def unmirrored(pcm: PcmViews, swap: np.ndarray) -> PcmViews:
    """The views with the channels of their swapped groups (swap (V, G)) exchanged left for right."""
    if not swap.any():
        return pcm
    kp = np.asarray(pcm.keypoints, dtype=np.intp)
    chan = np.full(len(KEYPOINTS), -1)
    chan[kp] = np.arange(kp.size)
    partner = chan[MIRROR[kp]]  # (J,) the channel of each channel's mirror keypoint, -1: none
    flip = (swap @ GROUP_MASK[:, kp]) & (partner >= 0)[None, :]  # (V, J)
    v, j = np.nonzero(flip)
    maps, valid, visibility = pcm.maps.copy(), pcm.valid.copy(), pcm.visibility.copy()
    maps[v, j], valid[v, j], visibility[v, j] = pcm.maps[v, partner[j]], pcm.valid[v, partner[j]], pcm.visibility[v, partner[j]]
    return dataclasses.replace(pcm, maps=maps, valid=valid, visibility=visibility)
