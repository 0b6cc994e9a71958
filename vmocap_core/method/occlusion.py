"""Which keypoints of a tracked person a camera cannot see: another tracked person hides
them, or they lie outside its image (several people; our extension, the paper tracks one
person).

A person who walks behind another is covered in some views: that view's crop holds the other
body in front, and its maps for the covered keypoints peak on the other body's limbs. The
lattice search (eq. 2) would add those peaks to the sum, and the consistency check would count
the view as disagreeing, so the person went uncertain (no output) while the other views saw
them well. `hidden_keypoints` finds the covered keypoints from the skeletons alone, each body a
set of capsules (its segments, with a radius each) at the segment's own depth, and
`without_hidden` marks them invalid in that person's views (PcmViews.valid): the search and
the check then use the views that see them. The marker stage does the same for a keypoint
outside a camera's image (a person leaving the room, one person or several): the landmark model
still places it, guessed from the rest of the body, and a body held by such guesses drifted
100 mm off while the check agreed with it.
"""

from __future__ import annotations

import dataclasses

import numpy as np

from ..cameras.projection import Rig
from ..keypoints import INDEX
from ..pcm.views import PcmViews

# A body's segments as capsules: (from, to, radius in metres). Limbs about as thick as a limb,
# the trunk as its lines from shoulders to hips, and the head around the neck-nose line.
_CAPSULES = (
    ("left_shoulder", "left_elbow", 0.06), ("left_elbow", "left_wrist", 0.05),
    ("right_shoulder", "right_elbow", 0.06), ("right_elbow", "right_wrist", 0.05),
    ("left_hip", "left_knee", 0.08), ("left_knee", "left_ankle", 0.06),
    ("right_hip", "right_knee", 0.08), ("right_knee", "right_ankle", 0.06),
    ("left_shoulder", "left_hip", 0.08), ("right_shoulder", "right_hip", 0.08),
    ("neck", "pelvis", 0.12), ("left_shoulder", "right_shoulder", 0.06), ("left_hip", "right_hip", 0.08),
    ("neck", "nose", 0.10),
)
_FROM = np.array([INDEX[a] for a, _, _ in _CAPSULES])
_TO = np.array([INDEX[b] for _, b, _ in _CAPSULES])
_RADIUS = np.array([r for _, _, r in _CAPSULES])
IN_FRONT_M = 0.15  # the covering body is at least this much nearer the camera than the keypoint


def hidden_keypoints(rig: Rig, bodies: np.ndarray) -> np.ndarray:
    """(P, C, 25) bool: keypoint k of body p (bodies (P, 25, 3), NaN: unknown) lies, in camera
    c, inside another body's projected capsule that is IN_FRONT_M nearer that camera."""
    P, K = bodies.shape[:2]
    C = len(rig)
    hidden = np.zeros((P, C, K), dtype=bool)
    if P < 2:
        return hidden
    pts = np.nan_to_num(np.asarray(bodies, dtype=np.float64)).reshape(-1, 3)
    cam = rig.to_camera_frames(pts)  # (C, P*K, 3)
    uv, front = rig.project_camera_points(cam)
    uv, z = uv.reshape(C, P, K, 2), cam[..., 2].reshape(C, P, K)
    known = (np.isfinite(bodies).all(axis=-1)[None] & front.reshape(C, P, K))  # (C, P, K)
    a, b = uv[:, :, _FROM], uv[:, :, _TO]  # (C, P, S, 2): every body's capsule axes
    za, zb = z[:, :, _FROM], z[:, :, _TO]
    axis = b - a
    length2 = np.maximum((axis ** 2).sum(-1), 1e-9)
    # keypoint (C, P, 1, K) against the capsules of every body (C, 1, P', S)
    q = uv[:, :, None, None, :, :]  # (C, P, 1, 1, K, 2)
    a_, axis_ = a[:, None, :, :, None, :], axis[:, None, :, :, None, :]  # (C, 1, P', S, 1, 2)
    t = np.clip(((q - a_) * axis_).sum(-1) / length2[:, None, :, :, None], 0.0, 1.0)  # (C, P, P', S, K)
    dist = np.linalg.norm(q - (a_ + t[..., None] * axis_), axis=-1)
    depth = za[:, None, :, :, None] + t * (zb - za)[:, None, :, :, None]  # the capsule's depth there
    focal = np.array([c.K[0, 0] for c in rig])[:, None, None, None, None]
    radius_px = _RADIUS[None, None, None, :, None] * focal / np.maximum(depth, 1e-3)
    seg_ok = (known[:, :, _FROM] & known[:, :, _TO])[:, None, :, :, None]  # (C, 1, P', S, 1)
    covers = seg_ok & (dist < radius_px) & (depth < z[:, :, None, None, :] - IN_FRONT_M)
    covers &= ~np.eye(P, dtype=bool)[None, :, :, None, None]  # a body does not hide itself
    hidden = covers.any(axis=(2, 3)) & known  # (C, P, K)
    return hidden.transpose(1, 0, 2)


def outside_images(rig: Rig, bodies: np.ndarray) -> np.ndarray:
    """(P, C, 25) bool: keypoint k of body p (bodies (P, 25, 3)) projects outside camera c's
    image, or lies behind it."""
    uv, front = rig.project(np.nan_to_num(np.asarray(bodies, dtype=np.float64)))  # (C, P, 25, 2), (C, P, 25)
    size = np.array([[c.width, c.height] for c in rig], dtype=np.float64)[:, None, None, :]
    inside = front & (uv >= 0).all(axis=-1) & (uv <= size - 1).all(axis=-1)
    return (~inside & np.isfinite(bodies).all(axis=-1)[None]).transpose(1, 0, 2)


def without_hidden(pcm: PcmViews, hidden: np.ndarray) -> PcmViews:
    """The views with the keypoints hidden from their camera (hidden (C, 25)) marked invalid."""
    if pcm.n_views == 0 or not hidden.any():
        return pcm
    cover = hidden[np.asarray(pcm.camera, dtype=np.intp)][:, np.asarray(pcm.keypoints, dtype=np.intp)]
    return dataclasses.replace(pcm, valid=pcm.valid & ~cover)
