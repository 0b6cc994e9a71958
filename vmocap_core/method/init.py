"""Initialization (paper II-C): the subject's skeleton from triangulated PCM centroids.

`triangulated_markers` gives the markers of a frame set while nobody is tracked; once enough
consecutive frame sets agree, `fit_skeleton` identifies the link lengths (medians over the
frames), the waist height, the face and foot offsets, and fits the initial pose.
"""

from __future__ import annotations

import dataclasses
from collections import deque
from typing import Any

import numpy as np
import pinocchio as pin

from ..cameras.projection import Rig
from ..keypoints import INDEX
from ..pcm.views import PcmViews
from .config import MarkersConfig
from .ik import solve_ik
from .init_report import CORE, camera_mask
from .landmarks import LandmarkModel, trunk_axes
from .results import N_KP, NECK, PELVIS, TRUNK, Markers, nan_markers
from .skeleton import BodyDimensions, Skeleton
from .triangulation import triangulate_robust


def triangulated_markers(rig: Rig, pcm: PcmViews, cfg: MarkersConfig) -> Markers:
    """Markers of II-C: each keypoint's PCM centroids triangulated robustly, where the views
    agree within init_max_reprojection_px; the weight is the sum of the centroids' peaks."""
    uv, peak = pcm.centroids(threshold=cfg.init_min_peak)  # (V, J, 2), (V, J)
    C = len(rig)
    # One observation per camera: where a camera has several views of a channel, the
    # strongest one.
    cam_uv = np.zeros((C, pcm.keypoints.size, 2))
    cam_w = np.zeros((C, pcm.keypoints.size))
    for v in np.argsort(peak.max(axis=1)):
        c = pcm.camera[v]
        better = peak[v] > cam_w[c]
        cam_uv[c, better] = uv[v, better]
        cam_w[c, better] = peak[v, better]
    pts, resid = triangulate_robust(rig, cam_uv, cam_w, cfg.init_max_reprojection_px, cfg.min_views)
    agree = np.isfinite(resid) & (resid <= cfg.init_max_reprojection_px)
    out = nan_markers(pcm.stamp_ns, "triangulated")
    out.positions[pcm.keypoints[agree]] = pts[agree]
    w = np.where(agree, cam_w.sum(axis=0), 0.0)
    out.weights[pcm.keypoints] = w
    n_cam = max(len(np.unique(pcm.camera)), 1)
    out.score = float(w.sum() / (n_cam * max(pcm.keypoints.size, 1)))
    out.residual_px = np.full(N_KP, np.nan)
    out.residual_px[pcm.keypoints] = resid
    out.cameras = np.zeros(N_KP, np.uint32)
    out.cameras[pcm.keypoints] = camera_mask(cam_w)
    presence = np.full(C, -1.0)
    np.maximum.at(presence, np.asarray(pcm.camera, dtype=np.intp), np.asarray(pcm.presence, dtype=np.float64))
    out.presence = {rig[c].name: float(presence[c]) for c in range(C) if presence[c] >= 0}
    return out


_CORE = np.array([INDEX[n] for n in CORE])
_TRUNK = np.r_[TRUNK, NECK, PELVIS]
_WHOLE = np.union1d(_CORE, _TRUNK)


class InitFrames:
    """The consecutive frame sets whose triangulated keypoints an initialization is fitted on
    (II-C): the views must agree on the core keypoints in each of the last `n`. With
    `limb_gaps` (an identification phase identifies the link lengths again afterwards), a wrist
    or ankle whose views disagree in one of them (crossing another body, an image's edge) leaves
    a gap in its own link's median only: the trunk in each frame set, each core keypoint in most
    of them and in the last, which the first pose is fitted to. Without that phase these frame
    sets are all the link lengths come from."""

    def __init__(self, n: int, limb_gaps: bool) -> None:
        self.n, self.limb_gaps = n, limb_gaps
        self._frames: deque[np.ndarray] = deque(maxlen=n)

    def clear(self) -> None:
        self._frames.clear()

    def drop_oldest(self) -> None:
        self._frames.popleft()

    def add(self, positions: np.ndarray) -> np.ndarray | None:
        """This frame set's triangulated keypoints (25, 3; NaN unknown) -> the frame sets to fit
        (n, 25, 3), or None while they are not there."""
        seen = np.isfinite(with_midpoints(positions[None])[0]).all(axis=1)
        if not seen[_TRUNK if self.limb_gaps else _WHOLE].all():
            self._frames.clear()
            return None
        self._frames.append(positions.copy())
        frames = np.array(self._frames)
        if (len(frames) < self.n or not seen[_CORE].all()
                or (np.isfinite(frames[:, _CORE, 0]).sum(axis=0) <= self.n // 2).any()):
            return None
        return frames


def with_midpoints(p: np.ndarray) -> np.ndarray:
    """Fill neck/pelvis from the shoulder/hip midpoints where a PCM model lacks them."""
    p = p.copy()
    for mid, (a, b) in (("neck", ("left_shoulder", "right_shoulder")), ("pelvis", ("left_hip", "right_hip"))):
        miss = ~np.isfinite(p[..., INDEX[mid], 0])
        p[..., INDEX[mid], :] = np.where(miss[..., None], 0.5 * (p[..., INDEX[a], :] + p[..., INDEX[b], :]), p[..., INDEX[mid], :])
    return p


def _shoulder_offsets(p: np.ndarray) -> tuple[float, float]:
    """Shoulder centre relative to the neck in the trunk frame (x forward, z from the pelvis
    to the neck): (forward, drop), medians over frames."""
    neck, ls, rs = p[:, INDEX["neck"]], p[:, INDEX["left_shoulder"]], p[:, INDEX["right_shoulder"]]
    x, _, z = trunk_axes(ls, rs, p[:, INDEX["pelvis"]], neck)
    d = 0.5 * (ls + rs) - neck
    fwd = np.sum(d * x, axis=1)
    up = np.sum(d * z, axis=1)
    ok = np.isfinite(fwd) & np.isfinite(up)
    if not ok.any():
        return 0.0, BodyDimensions().shoulder_drop
    return float(np.median(fwd[ok])), float(-np.median(up[ok]))


def _landmark_neck(p: np.ndarray, landmarks: LandmarkModel) -> np.ndarray:
    """(N, 3) necks of joint-centre frames p (N, 25, 3) where the model puts its neck: at the
    shoulder landmarks' midpoint, i.e. the shoulder centres' midpoint moved by the shoulder
    offset's x and z in the trunk frame. The trunk length is measured to this neck: to the
    centres' midpoint, it would put the skeleton's shoulders the offset's z too high, and the IK
    would bend the waist in every pose to bring them down."""
    x_off, _, z_off = landmarks.offsets[INDEX["left_shoulder"]]
    ls, rs = p[:, INDEX["left_shoulder"]], p[:, INDEX["right_shoulder"]]
    mid = 0.5 * (ls + rs)
    x, _, z = trunk_axes(ls, rs, p[:, INDEX["pelvis"]], mid)
    return mid + x_off * x + z_off * z


def identify_dimensions(frames: np.ndarray, landmarks: LandmarkModel | None = None) -> BodyDimensions:
    """Link lengths from triangulated keypoints (N, 25, 3): medians over frames (II-C).
    Joint centres of a CNN with `landmarks` and no neck landmark: the neck stays at the
    shoulder landmarks' midpoint (LandmarkModel.neck_dimensions)."""
    neck_seen = bool(np.isfinite(frames[..., INDEX["neck"], :]).all(axis=-1).any())
    p = with_midpoints(frames)
    if landmarks is not None and not neck_seen:
        p[:, INDEX["neck"]] = _landmark_neck(p, landmarks)

    def dist(a: str, b: str) -> float:
        d = np.linalg.norm(p[:, INDEX[a]] - p[:, INDEX[b]], axis=1)
        d = d[np.isfinite(d)]
        return float(np.median(d)) if d.size else float("nan")

    def both(a: str, b: str) -> float:
        vals = np.array([dist(f"left_{a}", f"left_{b}"), dist(f"right_{a}", f"right_{b}")])
        vals = vals[np.isfinite(vals)]
        return float(vals.mean()) if vals.size else float("nan")

    base = BodyDimensions()
    sw = dist("left_shoulder", "right_shoulder")
    fwd, drop = _shoulder_offsets(p)
    trunk = dist("pelvis", "neck")
    scale = trunk / base.trunk if np.isfinite(trunk) else 1.0
    dims = dataclasses.replace(
        base,
        hip_width=dist("left_hip", "right_hip"),
        thigh=both("hip", "knee"),
        shank=both("knee", "ankle"),
        trunk=trunk,
        shoulder_width=sw,
        shoulder_drop=drop,
        shoulder_forward=fwd,
        upper_arm=both("shoulder", "elbow"),
        forearm=both("elbow", "wrist"),
        nose=tuple(np.array(base.nose) * scale),
        eye=tuple(np.array(base.eye) * scale),
        ear=tuple(np.array(base.ear) * scale),
    )
    if landmarks is not None and not neck_seen:
        dims = dataclasses.replace(dims, **landmarks.neck_dimensions())
    hand = both("wrist", "hand")
    if np.isfinite(hand):
        dims = dataclasses.replace(dims, hand=hand)
    for name in ("heel", "toe"):
        length = both("ankle", name)
        if np.isfinite(length):
            v = np.array(getattr(base, name))
            dims = dataclasses.replace(dims, **{name: tuple(v / np.linalg.norm(v) * length)})
    return dims


# Keypoints that are not joint centres, and the BodyDimensions field of their offset in the
# parent joint's frame (left side; the right side mirrors y).
OFFSET_FIELDS = {"nose": "nose", "left_eye": "eye", "right_eye": "eye", "left_ear": "ear", "right_ear": "ear",
                 "left_heel": "heel", "right_heel": "heel", "left_toe": "toe", "right_toe": "toe"}


def frame_poses(skeleton: Skeleton, frames: np.ndarray, q0: np.ndarray) -> list[np.ndarray]:
    """The skeleton's pose fitted to each of the frames (N, 25, 3; NaN unknown), warm-started
    from q0 and then from the previous frame."""
    poses, q = [], q0
    for f in frames:
        ok = np.isfinite(f).all(axis=1).astype(float)
        q = solve_ik(skeleton, q, f, ok, 30, damping=1e-2, regularization=1e-6, line_search=True).q
        poses.append(q)
    return poses


def refine_offsets(skeleton: Skeleton, frames: np.ndarray, q0: np.ndarray, rounds: int = 2) -> Skeleton:
    """Identify the offsets of face and foot keypoints on the subject (II-C identifies link
    lengths; these are the rest of the body's geometry): alternate IK over the initialization
    frames with the median of each keypoint's coordinates in its parent joint's frame,
    left and mirrored right averaged. Keypoints seen in fewer than half the frames keep the
    scaled defaults."""
    seen = np.isfinite(frames).all(axis=2)  # (N, 25)
    names = [n for n in OFFSET_FIELDS if seen[:, INDEX[n]].sum() >= max(2, len(frames) // 2)]
    if not names:
        return skeleton
    sk = skeleton
    for _ in range(rounds):
        samples: dict[str, list[np.ndarray]] = {n: [] for n in names}
        for f, ok, q in zip(frames, seen, frame_poses(sk, frames, q0)):
            pin.forwardKinematics(sk.model, sk.data, q)
            R, t = sk._placements()
            for n in names:
                if ok[INDEX[n]]:
                    jid = sk._parent[INDEX[n]]
                    samples[n].append(R[jid].T @ (f[INDEX[n]] - t[jid]))
        fields: dict[str, list[np.ndarray]] = {}
        for n in names:
            off = np.median(np.array(samples[n]), axis=0)
            fields.setdefault(OFFSET_FIELDS[n], []).append(off * ([1.0, -1.0, 1.0] if n.startswith("right_") else 1.0))
        sk = Skeleton(dataclasses.replace(sk.dims, **{k: tuple(float(x) for x in np.mean(v, axis=0)) for k, v in fields.items()}))
    return sk


def initial_pose(skeleton: Skeleton, keypoints: np.ndarray) -> np.ndarray:
    """A configuration with the root at the pelvis, oriented by the hips and trunk, limbs
    neutral: the starting point of the initial IK."""
    p = with_midpoints(keypoints[None])[0]
    q = skeleton.neutral()
    y = p[INDEX["left_hip"]] - p[INDEX["right_hip"]]
    z = p[INDEX["neck"]] - p[INDEX["pelvis"]]
    if np.all(np.isfinite(y)) and np.all(np.isfinite(z)):
        y /= np.linalg.norm(y)
        z -= y * (z @ y)
        z /= np.linalg.norm(z)
        R = np.stack([np.cross(y, z), y, z], axis=1)
        q[3:7] = pin.Quaternion(R).coeffs()
    if np.all(np.isfinite(p[INDEX["pelvis"]])):
        q[:3] = p[INDEX["pelvis"]]
    return q


def length_offset(new: dict[str, float], old: dict[str, float]) -> float:
    """How far one body's link lengths are from another's: |median ratio - 1| (inf: none known in both)."""
    ratios = np.array([new[k] / old[k] for k in old if old[k] > 0 and k in new])
    ratios = ratios[np.isfinite(ratios)]
    return abs(float(np.median(ratios)) - 1.0) if ratios.size else np.inf


def fit_skeleton(frames: np.ndarray, max_fit_error_m: float, q0: np.ndarray | None = None,
                 landmarks: LandmarkModel | None = None) -> tuple[Skeleton, Any] | None:
    """Identify a skeleton on keypoint frames (N, 25, 3; NaN unknown) and fit it to the last
    frame: link lengths (II-C), the waist height by the fit it gives, face/foot offsets. None
    when the fit's RMS stays above `max_fit_error_m` (the frames do not show one body).

    With `landmarks` the frames are the CNN's landmarks: a first skeleton fitted to them gives
    each frame's segment orientations, the landmark offsets turned by those are removed, and
    the skeleton is identified again on the joint centres so found."""
    fitted = _fit_skeleton(frames, max_fit_error_m, q0)
    if fitted is None or landmarks is None:
        return fitted
    sk, fit = fitted
    centres = np.array([f - landmarks.correction(sk, q) for f, q in zip(frames, frame_poses(sk, frames, fit.q))])
    return _fit_skeleton(centres, max_fit_error_m, fit.q, landmarks)


def _fit_skeleton(frames: np.ndarray, max_fit_error_m: float, q0: np.ndarray | None,
                  landmarks: LandmarkModel | None = None) -> tuple[Skeleton, Any] | None:
    dims = identify_dimensions(frames, landmarks)
    last = frames[-1]
    w = np.where(np.isfinite(last).all(axis=1), 1.0, 0.0)
    best = None
    # The waist joint is not a keypoint: choose its height by the fit it gives.
    for ratio in (0.2, 0.35, 0.5, 0.65):
        sk = Skeleton(dataclasses.replace(dims, waist_ratio=ratio))
        q = initial_pose(sk, last) if q0 is None else q0
        fit = solve_ik(sk, q, last, w, 60, damping=1e-2, regularization=1e-6, line_search=True)
        rms = float(np.sqrt(fit.cost))
        if best is None or rms < best[0]:
            best = (rms, sk, fit)
    assert best is not None  # the loop above ran
    rms, sk, fit = best
    if rms <= max_fit_error_m:
        sk = refine_offsets(sk, frames, fit.q)
        fit = solve_ik(sk, fit.q, last, w, 30, damping=1e-2, regularization=1e-6, line_search=True)
        rms = float(np.sqrt(fit.cost))
    return (sk, fit) if rms <= max_fit_error_m else None
