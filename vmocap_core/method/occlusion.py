"""Which keypoints of a tracked person a camera cannot see: another tracked person hides
them, or they lie outside its image (several people; our extension, the paper tracks one
person).

Two people face to face (a handshake, a hug) overlap in every view: where one is in front, the
other's crop holds that body in front; where one is behind, its face and limbs show around the
other's outline, and the landmark model (a one-person model) reads the more visible body. In
both cases the track slid off its person within a second. `others_greyed` greys, in each
person's copy of an image, the other tracked bodies' capsules outside the person's own: the
crop then shows one person.

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
from typing import Sequence

import cv2
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


GREY = 127  # what a greyed pixel holds (the detector's `hidden` boxes use the same)
# drawn for greying, beyond the capsules above: hands, feet and the head around the ears (a
# hand or a head left showing is a person to the landmark model), every radius grown a little
# for clothes and a heavier build than the capsules' limbs
_DRAWN = _CAPSULES + (
    ("left_wrist", "left_hand", 0.05), ("right_wrist", "right_hand", 0.05),
    ("left_ankle", "left_toe", 0.05), ("right_ankle", "right_toe", 0.05),
    ("left_ankle", "left_heel", 0.05), ("right_ankle", "right_heel", 0.05),
    ("left_ear", "right_ear", 0.09),
)
_DRAWN_FROM = np.array([INDEX[a] for a, _, _ in _DRAWN])
_DRAWN_TO = np.array([INDEX[b] for _, b, _ in _DRAWN])
_DRAWN_RADIUS = 1.25 * np.array([r for _, _, r in _DRAWN])


def _silhouette(uv: np.ndarray, z: np.ndarray, known: np.ndarray, focal: float, roi: tuple[int, int, int, int]) -> np.ndarray | None:
    """(h, w) uint8 (1: inside) over roi (x0, y0, x1, y1) of the image: a body's capsules drawn from its
    keypoints' pixels (25, 2), depths (25,) and known-and-in-front flags (25,) in one camera
    (None: no capsule there)."""
    ok = known[_DRAWN_FROM] & known[_DRAWN_TO]
    if not ok.any():
        return None
    width = np.maximum(2.0 * _DRAWN_RADIUS * focal / np.maximum(0.5 * (z[_DRAWN_FROM] + z[_DRAWN_TO]), 1e-3), 1.0)
    x0, y0, x1, y1 = roi
    lim = 1 << 20  # cv2 takes int32 points; the drawing clips far-off ones anyway
    a = np.clip(np.round(uv[_DRAWN_FROM] - (x0, y0)), -lim, lim).astype(np.int64)
    b = np.clip(np.round(uv[_DRAWN_TO] - (x0, y0)), -lim, lim).astype(np.int64)
    mask = np.zeros((y1 - y0, x1 - x0), dtype=np.uint8)
    for s in np.flatnonzero(ok):  # one draw per capsule (21 per body): the raster is C-speed
        cv2.line(mask, (int(a[s, 0]), int(a[s, 1])), (int(b[s, 0]), int(b[s, 1])), 1,
                 thickness=int(np.ceil(width[s])), lineType=cv2.LINE_8)
    return mask


def _boxes(uv: np.ndarray, known: np.ndarray) -> np.ndarray:
    """(C, P, 4) each body's projected keypoints' box (x0, y0, x1, y1), NaN where none is known
    and in front; uv (C, P, 25, 2), known (C, P, 25)."""
    ok = known[..., None]
    lo = np.where(ok, uv, np.inf).min(axis=2)
    hi = np.where(ok, uv, -np.inf).max(axis=2)
    box = np.concatenate([lo, hi], axis=-1)
    return np.where(np.isfinite(box), box, np.nan)


def others_greyed(rig: Rig, images: Sequence[np.ndarray | None], bodies: np.ndarray,
                  whose: Sequence[int | None]) -> dict[tuple[int, int], np.ndarray]:
    """Per (entry of `whose`, camera): image c with the tracked bodies ((P, 25, 3)) other than
    body whose[i] greyed where their capsules lie outside body whose[i]'s own (whose[i] None:
    a person without a skeleton yet, every tracked body greyed). Only where another body's
    projected box overlaps that body's (or, for None, where some body is in the image): elsewhere
    the image is used as it is and has no entry. The drawing covers the others' boxes only."""
    out: dict[tuple[int, int], np.ndarray] = {}
    bodies = np.asarray(bodies, dtype=np.float64).reshape(-1, len(INDEX), 3)
    if len(bodies) == 0 or (len(bodies) < 2 and all(w is not None for w in whose)):
        return out
    cam = rig.to_camera_frames(np.nan_to_num(bodies))  # (C, P, 25, 3)
    uv, front = rig.project_camera_points(cam.reshape(len(rig), -1, 3))
    uv, z = uv.reshape(cam.shape[:-1] + (2,)), cam[..., 2]
    known = front.reshape(z.shape) & np.isfinite(bodies).all(axis=-1).reshape(1, *bodies.shape[:2])  # (C, P, 25)
    box = _boxes(uv, known)  # (C, P, 4)
    # a capsule reaches this far beyond its keypoints' box: the widest one at the body's nearest depth
    reach = _DRAWN_RADIUS.max() * np.array([c.K[0, 0] for c in rig])[:, None] / \
        np.maximum(np.nanmin(np.where(known, z, np.nan), axis=2), 1e-3)  # (C, P)
    for c, im in enumerate(images):
        if im is None:
            continue
        h, w = im.shape[:2]
        inside = np.isfinite(box[c]).all(axis=1) & (box[c, :, 0] < w) & (box[c, :, 2] > 0) & \
            (box[c, :, 1] < h) & (box[c, :, 3] > 0)
        lo, hi = box[c, :, :2], box[c, :, 2:]
        for i, p in enumerate(whose):
            if p is None:
                others = [q for q in range(len(bodies)) if inside[q]]
            else:
                overlap = (lo < hi[p]).all(axis=1) & (hi > lo[p]).all(axis=1) & inside
                others = [int(q) for q in np.flatnonzero(overlap) if q != p] if inside[p] else []
            if not others:
                continue
            grow = np.nan_to_num(reach[c, others], nan=0.0)[:, None]
            x0, y0 = np.clip(np.floor((lo[others] - grow).min(axis=0)), 0, [w, h]).astype(int)
            x1, y1 = np.clip(np.ceil((hi[others] + grow).max(axis=0)), 0, [w, h]).astype(int)
            if x1 <= x0 or y1 <= y0:
                continue
            roi = (int(x0), int(y0), int(x1), int(y1))
            focal = float(rig[c].K[0, 0])
            masks = [m for m in (_silhouette(uv[c, q], z[c, q], known[c, q], focal, roi) for q in others) if m is not None]
            if not masks:
                continue
            grey = masks[0]
            for m in masks[1:]:
                grey = cv2.bitwise_or(grey, m)
            own = _silhouette(uv[c, p], z[c, p], known[c, p], focal, roi) if p is not None else None
            if own is not None:
                grey = cv2.subtract(grey, own)  # saturating: 1 only where another body is and this one is not
            copy = im.copy()
            cv2.copyTo(np.full((y1 - y0, x1 - x0) + im.shape[2:], GREY, dtype=im.dtype), grey, copy[y0:y1, x0:x1])
            out[(i, c)] = copy
    return out
