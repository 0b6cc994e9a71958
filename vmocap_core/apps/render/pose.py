"""Posing the body from 14 keypoints: one affine transform per rigid segment, then linear
blend skinning.

Each segment gets an orthonormal frame (r, a x r, a) in the rest pose and in every frame of
the clip: `a` along the bone, `r` the twist reference (trunk: the hip or shoulder line;
limbs: the bend direction of the next bone, blended into the trunk's forward direction as
the limb straightens; hands, feet and head ride on their parent's frame). The transform maps
rest frame to clip frame and stretches along the bone so that both joint centres of a bone
land on the clip's keypoints: the body takes the clip's bone lengths, the truth is the clip.
"""

from __future__ import annotations

import numpy as np

from ...errors import VmocapError
from .body import SEGMENT_NAMES, Body

CLIP_KEYPOINTS = ("pelvis", "neck", "right_shoulder", "right_elbow", "right_wrist", "left_shoulder", "left_elbow",
                  "left_wrist", "right_hip", "right_knee", "right_ankle", "left_hip", "left_knee", "left_ankle")
SIDES = (("l", "left"), ("r", "right"))
# bones whose length ratio (clip / rest) sets the girth scale of the whole body
_SIZE_BONES = (("pelvis", "neck"), ("left_hip", "left_knee"), ("left_knee", "left_ankle"),
               ("right_hip", "right_knee"), ("right_knee", "right_ankle"), ("left_shoulder", "left_elbow"),
               ("right_shoulder", "right_elbow"))


def _unit(v: np.ndarray) -> np.ndarray:
    return v / np.maximum(np.linalg.norm(v, axis=-1, keepdims=True), 1e-12)


def _perp(v: np.ndarray, a: np.ndarray) -> np.ndarray:
    """Component of v perpendicular to the unit vector a."""
    return v - np.sum(v * a, axis=-1, keepdims=True) * a


def _frame(r: np.ndarray, a: np.ndarray) -> np.ndarray:
    """(..., 3, 3) basis with columns r, a x r, a (r made perpendicular to a)."""
    r = _unit(_perp(r, a))
    return np.stack([r, np.cross(a, r), a], axis=-1)


def _limb_ref(axis: np.ndarray, bend: np.ndarray, fallback: np.ndarray, length: np.ndarray) -> np.ndarray:
    """Twist reference of a limb's proximal bone: the next bone's bend direction, blended into
    `fallback` while the limb is nearly straight (the bend is undefined there)."""
    b = _perp(bend, axis)
    w = np.clip(np.linalg.norm(b, axis=-1, keepdims=True) / (0.25 * length[..., None]), 0.0, 1.0)
    return _unit(w * _unit(b) + (1.0 - w) * _unit(_perp(fallback, axis)))


def segment_frames(J: dict[str, np.ndarray]) -> dict[str, tuple[np.ndarray, np.ndarray, np.ndarray]]:
    """Per segment: origin (..., 3), basis (..., 3, 3), bone length (...) (0 for rigid riders)."""
    pel, neck = J["pelvis"], J["neck"]
    up = _unit(neck - pel)
    trunk_len = np.linalg.norm(neck - pel, axis=-1)
    pelvis_B = _frame(J["left_hip"] - J["right_hip"], up)
    chest_B = _frame(J["left_shoulder"] - J["right_shoulder"], up)
    zero = np.zeros_like(trunk_len)
    out = {"pelvis": (pel, pelvis_B, trunk_len), "chest": (pel, chest_B, trunk_len), "head": (neck, chest_B, zero)}
    fwd_chest = chest_B[..., 1] * -1.0  # a x r points backwards for r = left, a = up
    fwd_pelvis = pelvis_B[..., 1] * -1.0
    for s, side in SIDES:
        sh, el, wr = J[f"{side}_shoulder"], J[f"{side}_elbow"], J[f"{side}_wrist"]
        hip, kn, an = J[f"{side}_hip"], J[f"{side}_knee"], J[f"{side}_ankle"]
        a = _unit(sh - neck)
        out[f"clavicle_{s}"] = (neck, _frame(fwd_chest, a), np.linalg.norm(sh - neck, axis=-1))
        for prox, (j0, j1, j2), sign, fwd in (("arm", (sh, el, wr), 1.0, fwd_chest), ("leg", (hip, kn, an), -1.0, fwd_pelvis)):
            a1, a2 = _unit(j1 - j0), _unit(j2 - j1)
            l1, l2 = np.linalg.norm(j1 - j0, axis=-1), np.linalg.norm(j2 - j1, axis=-1)
            r1 = _limb_ref(a1, sign * (j2 - j1), fwd, l2)
            # distal bone: in the limb plane, pointing where r1 points (two estimates that agree
            # when both are defined; their sum stays defined at a straight or a right-angle bend)
            r2 = _perp(-sign * a1, a2) + _perp(r1, a2)
            B1, B2 = _frame(r1, a1), _frame(r2, a2)
            n1, n2, n3 = ("upperarm", "forearm", "hand") if prox == "arm" else ("thigh", "shin", "foot")
            out[f"{n1}_{s}"] = (j0, B1, l1)
            out[f"{n2}_{s}"] = (j1, B2, l2)
            out[f"{n3}_{s}"] = (j2, B2, zero)
    return out


def clip_joints(positions: np.ndarray, names: tuple[str, ...] | list[str]) -> dict[str, np.ndarray]:
    """(T, J, 3) clip positions -> {keypoint: (T, 3)} for the 14 keypoints (all required)."""
    idx = {n: i for i, n in enumerate(names)}
    missing = [k for k in CLIP_KEYPOINTS if k not in idx]
    if missing:
        raise VmocapError(f"rendering a body needs all 14 clip keypoints; missing {missing}")
    J = {k: np.asarray(positions[:, idx[k]], dtype=np.float64) for k in CLIP_KEYPOINTS}
    if not all(np.isfinite(v).all() for v in J.values()):
        raise VmocapError("the clip has non-finite keypoints")
    return J


def girth_scale(body: Body, J: dict[str, np.ndarray]) -> float:
    """Clip size / body size over the long bones: scales the body across its bones."""
    clip = sum(np.median(np.linalg.norm(J[b] - J[a], axis=-1)) for a, b in _SIZE_BONES)
    rest = sum(np.linalg.norm(body.joints[b] - body.joints[a]) for a, b in _SIZE_BONES)
    return float(clip / rest)


def segment_transforms(body: Body, J: dict[str, np.ndarray]) -> tuple[np.ndarray, np.ndarray]:
    """Affine maps rest -> clip per frame and segment: A (T, S, 3, 3), b (T, S, 3)."""
    rest = segment_frames(body.joints)
    pose = segment_frames(J)
    g = girth_scale(body, J)
    T = next(iter(J.values())).shape[0]
    A = np.empty((T, len(SEGMENT_NAMES), 3, 3))
    b = np.empty((T, len(SEGMENT_NAMES), 3))
    hip_w_rest = np.linalg.norm(body.joints["left_hip"] - body.joints["right_hip"])
    hip_w = np.linalg.norm(J["left_hip"] - J["right_hip"], axis=-1)
    for s, name in enumerate(SEGMENT_NAMES):
        o_r, B_r, L_r = rest[name]
        o_p, B_p, L_p = pose[name]
        scale = np.full((T, 3), g)
        if L_r > 0:
            scale[:, 2] = L_p / L_r  # stretch along the bone to the clip's length
        if name == "pelvis":
            scale[:, 0] = hip_w / hip_w_rest  # hip joints on the clip's hips
        A[:, s] = np.einsum("tij,tj,kj->tik", B_p, scale, B_r)
        b[:, s] = o_p - A[:, s] @ o_r
    return A, b


def skin(body: Body, A: np.ndarray, b: np.ndarray) -> np.ndarray:
    """Linear blend skinning of one frame: A (S, 3, 3), b (S, 3) -> vertices (V, 3)."""
    per_seg = np.einsum("sij,vj->vsi", A, body.vertices) + b[None]
    return np.einsum("vs,vsi->vi", body.weights, per_seg)
