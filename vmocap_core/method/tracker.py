"""The spatiotemporal filter of the paper, split in the two stages the node graph runs.

MarkerStage   (II-C, II-D): PCMs -> virtual markers. Initialization triangulates PCM
              centroids; tracking runs the lattice search around the skeleton of the previous
              frame. Detects a lost person (score below a threshold for N frames).
SkeletonStage (II-C, II-E, II-F): markers -> skeleton. Identifies the subject's link lengths
              and initial pose once the views agree in 3D, then per frame: weighted IK to the
              virtual markers, IIR low-pass of the keypoint positions, second IK to the
              filtered positions (smooth output with constant link lengths).
SpatiotemporalFilter wires both with the feedback of the first IK's keypoints.
"""

from __future__ import annotations

import dataclasses
import time
from collections import deque
from dataclasses import dataclass, field
from typing import Any

import numpy as np
import pinocchio as pin

from ..cameras.projection import Rig
from ..keypoints import INDEX, KEYPOINTS
from ..pcm.views import PcmViews
from .iir import LowPassFilter
from .ik import solve_ik
from .ik import warm_up as warm_up_ik
from .init_report import CORE, camera_mask
from .lattice import PcmSampler, lattice_search
from .lattice import warm_up as warm_up_lattice
from .one_euro import OneEuroFilter
from .refinement import refine_markers
from .refinement import warm_up as warm_up_refinement
from .skeleton import BodyDimensions, Skeleton
from .smoothing import FixedLagSmoother, MotionModel
from .triangulation import triangulate_robust

N_KP = len(KEYPOINTS)


@dataclass
class TrackerConfig:
    """Every tunable of the filter; `from_dict` rejects unknown keys."""

    fps: float = 60.0
    # Lattice search (II-D)
    lattice_k: int = 5
    lattice_spacing: float = 0.02  # metres; sub-lattice refinement recovers the precision
    coarse_to_fine: bool = True  # same volume, ~9x fewer samples; measured equal to the full search
    subcell: bool = True
    prediction: str = "previous"  # lattice centre: "previous" (paper) or "constant_velocity"
    min_views: int = 2  # a marker seen by fewer views gets weight 0
    # Our addition (peak_refinement.py): move each lattice marker to the robust triangulation of
    # the views' own PCM peaks within `refine_radius_cells` of its projection (False = the
    # lattice argmax, as in the paper). W stays the lattice sum.
    refine_markers: bool = True
    refine_radius_cells: int = 5
    refine_max_error_px: float = 12.0
    reacquire_weight: float = 1.0  # a marker weaker than this triggers a search at its PCM peaks
    reacquire_radius: float = 0.6  # metres from the previous keypoint a re-acquired one may lie
    reacquire_after: int = 2  # consecutive weak frames before the search at the PCM peaks
    # IK (II-E)
    ik_iterations: int = 3  # first IK (to the virtual markers), warm-started
    second_ik_iterations: int = 1  # second IK (to the smoothed positions, which move little)
    ik_damping: float = 1e-3
    ik_regularization: float = 1e-5
    # Motion prior of the first IK (our addition): weight of the squared tangent-space distance
    # to the previous frame's pose, against the weighted mean squared marker residual (m^2),
    # given for 60 fps and scaled by (fps / 60)^2 (the motion per frame scales with 1 / fps).
    # Synthetic benchmark: regular 37.8 -> 30.7 mm with the filter below; Shelf (25 fps) PCP
    # 97.24 -> 97.40 %. A constant-velocity prediction as prior was worse (it extrapolates noise).
    ik_prior_weight: float = 2e-3
    second_ik_restart_m: float = 0.02  # RMS fit error of the second IK that triggers a restart
    # Low-pass filter (II-F): "one_euro" (our default, one_euro.py: first order, cutoff rising
    # with each keypoint's speed) or "butterworth" (the paper's fixed IIR, the settings below).
    # Synthetic benchmark against the best Butterworth found (first order, 3 Hz, lag
    # compensation; 2.5-6 Hz were no better): regular 28.7 -> 28.1 mm, inverted 26.3 -> 25.3 mm,
    # mean joint acceleration (jitter) 85.6 -> 82.9 m/s^2. beta 15-20 gave 27.6 mm but +8-18 %
    # jitter.
    filter_kind: str = "one_euro"
    filter_min_cutoff_hz: float = 1.0
    filter_beta: float = 10.0  # Hz of cutoff per m/s
    filter_derivative_cutoff_hz: float = 2.0
    # Butterworth: first order at 3 Hz with lag compensation; on the synthetic benchmark the
    # second-order 6 Hz filter overshot fast motions (run 48 vs 34 mm with the prior above).
    filter_order: int = 1
    filter_cutoff_hz: float = 3.0
    filter_lag_compensation: bool = True
    # Our addition, smoothing.py: a Rauch-Tung-Striebel smoother of the first IK's keypoints on
    # a kinematic motion model ("cv" constant velocity, "ca" constant acceleration).
    # smoothing_lag_frames > 0 replaces the low-pass above live: fixed-lag smoothing, each
    # output is the frame that many frames back (status "smoothing" while the window fills).
    smoothing_lag_frames: int = 0
    smoother_model: str = "ca"
    smoother_process_noise: float = 2000.0  # (m/s^3)^2/Hz for "ca", (m/s^2)^2/Hz for "cv"
    smoother_measurement_noise_m: float = 0.02
    # Offline mode (offline.py, whole recordings only): identification on all tracked frames,
    # first IK, fixed-interval smoothing ("rts" with the model above, or zero-phase "gaussian"),
    # second IK. Read by `vmocap process` and `vmocap bench accuracy`; the live tracker ignores it.
    offline: bool = False
    offline_smoother: str = "rts"
    offline_gaussian_sigma_frames: float = 1.5
    offline_ik_iterations: int = 3
    offline_ik_prior_weight: float = 5e-4  # weaker than live: the causal prior lags, the smoother does its work
    offline_second_ik_iterations: int = 3
    # Initialization (II-C)
    init_frames: int = 5  # consecutive agreeing frames needed
    # Our addition: after the provisional fit on those frames, track for this long (status
    # "identifying", no output) and identify the link lengths again from the virtual markers of
    # all those frames; output starts with these final lengths. 5 noisy frames left bones 2-4 cm
    # off on the synthetic benchmark: regular 30.7 -> 28.7 mm, inverted 28.6 -> 26.3 mm (1 s:
    # 0.3 mm better still). 0: the provisional fit is final (the paper).
    identify_seconds: float = 0.5
    init_max_reprojection_px: float = 12.0  # views agree: triangulation residual below this
    init_max_fit_error_m: float = 0.04  # skeleton fit residual (RMS) to confirm
    init_min_peak: float = 0.3  # a centroid counts when its PCM peak is at least this
    # Lost person
    lost_score: float = 0.15  # mean marker weight per view below this ...
    lost_frames: int = 10  # ... for this many frames -> re-initialize

    @classmethod
    def from_dict(cls, d: dict[str, Any] | None) -> "TrackerConfig":
        d = dict(d or {})
        names = {f.name for f in dataclasses.fields(cls)}
        unknown = sorted(set(d) - names)
        if unknown:
            raise ValueError(f"unknown tracker parameters: {', '.join(unknown)}")
        cfg = cls(**d)
        cfg.validate()
        return cfg

    def validate(self) -> None:
        if self.refine_radius_cells < 1 or self.refine_max_error_px <= 0:
            raise ValueError("refine_radius_cells must be >= 1 and refine_max_error_px > 0")
        if self.fps <= 0 or self.lattice_k < 0 or self.lattice_spacing <= 0:
            raise ValueError("fps, lattice_k and lattice_spacing must be positive")
        if self.identify_seconds < 0:
            raise ValueError("identify_seconds must be >= 0")
        if self.ik_prior_weight < 0 or self.ik_regularization < 0:
            raise ValueError("IK weights and regularizations must be >= 0")
        if self.prediction not in ("previous", "constant_velocity"):
            raise ValueError(f"prediction must be 'previous' or 'constant_velocity', not {self.prediction!r}")
        if not 0 < self.filter_cutoff_hz < self.fps / 2:
            raise ValueError("filter_cutoff_hz must be below half the frame rate")
        if self.filter_kind not in ("one_euro", "butterworth"):
            raise ValueError(f"filter_kind must be 'one_euro' or 'butterworth', not {self.filter_kind!r}")
        make_filter(self)  # the filter's own checks (cutoffs, order)
        if self.smoothing_lag_frames < 0 or self.offline_smoother not in ("rts", "gaussian"):
            raise ValueError("smoothing_lag_frames must be >= 0, offline_smoother 'rts' or 'gaussian'")
        if self.offline_ik_iterations < 1 or self.offline_second_ik_iterations < 1 or self.offline_ik_prior_weight < 0:
            raise ValueError("offline IK iterations must be >= 1 and the prior weight >= 0")
        smoother_model(self)  # the motion model's own checks

    @property
    def identify_frames(self) -> int:
        """Frames of the identification phase (identify_seconds at this frame rate)."""
        return round(self.identify_seconds * self.fps)

    def to_dict(self) -> dict[str, Any]:
        return dataclasses.asdict(self)


@dataclass
class Markers:
    """Virtual markers of one frame set, in KEYPOINTS order."""

    stamp_ns: int
    positions: np.ndarray  # (25, 3), NaN where unknown
    weights: np.ndarray  # (25,), 0 where unknown
    kind: str  # "triangulated" | "lattice" | "none"
    score: float = 0.0  # mean weight per view over the observed keypoints (0..1)
    # triangulated markers: what a stalled initialization is diagnosed from (init_report.py)
    residual_px: np.ndarray | None = None  # (25,) triangulation residual, NaN: not triangulated
    cameras: np.ndarray | None = None  # (25,) bit masks of the cameras whose peaks went in
    presence: dict[str, float] | None = None  # CNN presence per camera (not in messages)


def make_filter(config: TrackerConfig) -> LowPassFilter | OneEuroFilter:
    """The low-pass of II-F that `config` asks for (fresh state)."""
    if config.filter_kind == "one_euro":
        return OneEuroFilter(config.filter_min_cutoff_hz, config.filter_beta, config.fps, config.filter_derivative_cutoff_hz)
    return LowPassFilter(config.filter_order, config.filter_cutoff_hz, config.fps, config.filter_lag_compensation)


def smoother_model(config: TrackerConfig) -> MotionModel:
    """The kinematic model of the RTS smoothers (fixed-lag live, fixed-interval offline)."""
    return MotionModel(config.smoother_model, config.smoother_process_noise, config.smoother_measurement_noise_m,
                       config.fps)


# Statuses whose raw keypoints are fed back to the lattice search (the others re-initialize);
# only "tracking" results are output.
FEEDBACK_STATUSES = ("tracking", "identifying", "smoothing")


@dataclass
class TrackResult:
    stamp_ns: int
    status: str  # "initializing" | "identifying" | "smoothing" | "tracking" | "lost"
    q: np.ndarray  # (40,) published DOF after the second IK (see Skeleton.to_angles)
    joint_names: list[str]
    keypoints: np.ndarray  # (25, 3) filtered output
    raw_keypoints: np.ndarray  # (25, 3) first IK (fed back to the lattice search)
    scores: np.ndarray  # (25,) marker weights
    markers: np.ndarray  # (25, 3) virtual markers
    link_lengths: dict[str, float] = field(default_factory=dict)
    dims: BodyDimensions | None = None  # the subject's skeleton (tracking results only)


def trunk_tilt(rig: Rig, keypoints: np.ndarray) -> np.ndarray:
    """Per camera, the angle (radians, in (-pi, pi]) of the projected pelvis->neck vector from
    image-up: 0 upright, pi upside down. Rotating the input image by this angle makes the person
    upright for the CNN (paper III-B)."""
    pts = np.asarray(keypoints)[[INDEX["pelvis"], INDEX["neck"]]]
    uv, _ = rig.project(pts)  # (C, 2, 2)
    d = uv[:, 1] - uv[:, 0]
    return np.arctan2(d[:, 0], -d[:, 1])


def _nan_markers(stamp_ns: int, kind: str = "none") -> Markers:
    return Markers(stamp_ns, np.full((N_KP, 3), np.nan), np.zeros(N_KP), kind, 0.0)


class MarkerStage:
    """PCMs -> virtual markers (triangulated centroids while initializing, lattice search while
    tracking)."""

    def __init__(self, rig: Rig, config: TrackerConfig | None = None) -> None:
        self.rig = rig
        self.config = config or TrackerConfig()
        self.centres: np.ndarray | None = None  # skeleton keypoints of the previous frame
        self.velocity = np.zeros((N_KP, 3))
        self._low = 0
        self._weak = np.zeros(N_KP, dtype=np.int64)  # consecutive weak frames per keypoint
        self.timings: dict[str, float] = {}  # seconds spent in the last step, per stage
        warm_up_lattice(rig)
        warm_up_refinement(rig)

    @property
    def tracking(self) -> bool:
        return self.centres is not None

    def feedback(self, keypoints: np.ndarray | None) -> None:
        """The first-IK keypoints of the frame just processed, or None when not tracking."""
        if keypoints is None:
            self.centres = None
            self.velocity[:] = 0.0
            self._weak[:] = 0
            return
        kp = np.asarray(keypoints, dtype=np.float64)
        if self.centres is not None:
            self.velocity = kp - self.centres
        else:
            self.velocity[:] = 0.0
        self.centres = kp.copy()

    def step(self, pcm: PcmViews) -> Markers:
        t0 = time.perf_counter()
        if pcm.n_views == 0:
            out = _nan_markers(pcm.stamp_ns)
        elif self.centres is None:
            out = self._triangulate(pcm.sanitized())
        else:
            out = self._lattice(pcm)  # the lattice search sanitizes the values it reads
        self.timings = {"lattice": time.perf_counter() - t0}
        return out

    def _triangulate(self, pcm: PcmViews) -> Markers:
        cfg = self.config
        uv, peak = pcm.centroids(threshold=cfg.init_min_peak)  # (V, J, 2), (V, J)
        C = len(self.rig)
        # One observation per camera: where a camera has several views of a channel, the
        # strongest one.
        cam_uv = np.zeros((C, pcm.keypoints.size, 2))
        cam_w = np.zeros((C, pcm.keypoints.size))
        for v in np.argsort(peak.max(axis=1)):
            c = pcm.camera[v]
            better = peak[v] > cam_w[c]
            cam_uv[c, better] = uv[v, better]
            cam_w[c, better] = peak[v, better]
        pts, resid = triangulate_robust(self.rig, cam_uv, cam_w, cfg.init_max_reprojection_px, cfg.min_views)
        agree = np.isfinite(resid) & (resid <= cfg.init_max_reprojection_px)
        out = _nan_markers(pcm.stamp_ns, "triangulated")
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
        out.presence = {self.rig[c].name: float(presence[c]) for c in range(C) if presence[c] >= 0}
        return out

    def _lattice(self, pcm: PcmViews) -> Markers:
        cfg = self.config
        centres = self.centres
        assert centres is not None  # set by the previous frame's skeleton (markers run only while tracking)
        if cfg.prediction == "constant_velocity":
            centres = centres + self.velocity
        sampler = PcmSampler(self.rig, pcm)  # one per frame: the lattice search and the refinement
        res = lattice_search(
            self.rig,
            pcm,
            centres[pcm.keypoints],
            k=cfg.lattice_k,
            spacing=cfg.lattice_spacing,
            coarse_to_fine=cfg.coarse_to_fine,
            subcell=cfg.subcell,
            sampler=sampler,
        )
        markers, weights, n_views = res.markers, res.weights, res.n_views
        # A marker weak for `reacquire_after` frames in a row (one weak frame is usually a
        # view's missing PCM, not a lost keypoint).
        low = np.zeros(N_KP, dtype=bool)
        low[pcm.keypoints] = weights < cfg.reacquire_weight
        self._weak = np.where(low, self._weak + 1, 0)
        weak = self._weak[pcm.keypoints] >= cfg.reacquire_after
        if weak.any():
            markers, weights, n_views = self._reacquire(pcm, weak, markers, weights, n_views)
        seen = n_views >= cfg.min_views
        if cfg.refine_markers and seen.any():
            refined, ok = refine_markers(self.rig, pcm, markers, cfg.refine_radius_cells,
                                         max_error_px=cfg.refine_max_error_px, min_views=cfg.min_views,
                                         sampler=sampler)
            markers = np.where((ok & seen)[:, None], refined, markers)
        out = _nan_markers(pcm.stamp_ns, "lattice")
        out.positions[pcm.keypoints] = markers
        out.weights[pcm.keypoints] = np.where(seen, weights, 0.0)
        n_cam = max(len(np.unique(pcm.camera[pcm.valid.any(axis=1)])), 1)
        observed = max(int(pcm.valid.any(axis=0).sum()), 1)
        out.score = float(out.weights.sum() / (n_cam * observed))
        self._low = self._low + 1 if out.score < cfg.lost_score else 0
        if self._low >= cfg.lost_frames:
            # Lost: start over from triangulation with this very frame.
            self._low = 0
            self.feedback(None)
            return self._triangulate(pcm.sanitized())
        return out


    def _reacquire(self, pcm: PcmViews, weak: np.ndarray, markers: np.ndarray, weights: np.ndarray,
                   n_views: np.ndarray) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
        """Per-keypoint recovery (our addition to the paper): a keypoint whose lattice optimum
        is weak may have left the lattice (a fast limb). Triangulate its PCM peaks and search a
        lattice there too; keep whichever optimum has the higher summed score (eq. 1), and only
        within `reacquire_radius` of the previous skeleton, so another person cannot take it."""
        cfg = self.config
        sub = np.flatnonzero(weak)
        uv, val = pcm.peaks(sub)
        cam_uv = np.zeros((len(self.rig), sub.size, 2))
        cam_w = np.zeros((len(self.rig), sub.size))
        for v in range(pcm.n_views):  # a few views: merge them per camera (strongest wins)
            c = pcm.camera[v]
            better = val[v] > cam_w[c]
            cam_uv[c, better] = uv[v][better]
            cam_w[c, better] = val[v][better]
        pts, resid = triangulate_robust(self.rig, cam_uv, cam_w, cfg.init_max_reprojection_px, cfg.min_views)
        assert self.centres is not None  # called from _lattice
        near = np.linalg.norm(pts - self.centres[pcm.keypoints[sub]], axis=1) < cfg.reacquire_radius
        ok = np.isfinite(resid) & (resid <= cfg.init_max_reprojection_px) & near
        if not ok.any():
            return markers, weights, n_views
        cand = sub[ok]
        # The same maps with only the candidates valid: the kernel skips the other channels.
        only = np.zeros_like(pcm.valid)
        only[:, cand] = pcm.valid[:, cand]
        centres = markers.copy()
        centres[cand] = pts[ok]
        masked = PcmViews(pcm.maps, pcm.image_to_map, pcm.camera, pcm.keypoints, only, pcm.presence, pcm.stamp_ns)
        alt = lattice_search(self.rig, masked, centres, k=1, spacing=cfg.lattice_spacing, subcell=cfg.subcell)
        alt.markers, alt.weights, alt.n_views = alt.markers[cand], alt.weights[cand], alt.n_views[cand]
        better = alt.weights > weights[cand]
        markers, weights, n_views = markers.copy(), weights.copy(), n_views.copy()
        markers[cand[better]] = alt.markers[better]
        weights[cand[better]] = alt.weights[better]
        n_views[cand[better]] = alt.n_views[better]
        return markers, weights, n_views


def _with_midpoints(p: np.ndarray) -> np.ndarray:
    """Fill neck/pelvis from the shoulder/hip midpoints where a PCM model lacks them."""
    p = p.copy()
    for mid, (a, b) in (("neck", ("left_shoulder", "right_shoulder")), ("pelvis", ("left_hip", "right_hip"))):
        miss = ~np.isfinite(p[..., INDEX[mid], 0])
        p[..., INDEX[mid], :] = np.where(miss[..., None], 0.5 * (p[..., INDEX[a], :] + p[..., INDEX[b], :]), p[..., INDEX[mid], :])
    return p


def _shoulder_offsets(p: np.ndarray) -> tuple[float, float]:
    """Shoulder centre relative to the neck in the trunk frame (x forward, z from the pelvis
    to the neck): (forward, drop), medians over frames."""
    neck, pel = p[:, INDEX["neck"]], p[:, INDEX["pelvis"]]
    ls, rs = p[:, INDEX["left_shoulder"]], p[:, INDEX["right_shoulder"]]
    y = ls - rs
    y /= np.linalg.norm(y, axis=1, keepdims=True)
    z = neck - pel
    z -= y * np.sum(z * y, axis=1, keepdims=True)
    z /= np.linalg.norm(z, axis=1, keepdims=True)
    x = np.cross(y, z)
    d = 0.5 * (ls + rs) - neck
    fwd = np.sum(d * x, axis=1)
    up = np.sum(d * z, axis=1)
    ok = np.isfinite(fwd) & np.isfinite(up)
    if not ok.any():
        return 0.0, BodyDimensions().shoulder_drop
    return float(np.median(fwd[ok])), float(-np.median(up[ok]))


def identify_dimensions(frames: np.ndarray) -> BodyDimensions:
    """Link lengths from triangulated keypoints (N, 25, 3): medians over frames (II-C)."""
    p = _with_midpoints(frames)

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
        q = q0
        for f, ok in zip(frames, seen):
            q = solve_ik(sk, q, f, ok.astype(float), 30, damping=1e-2, regularization=1e-6, line_search=True).q
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
    p = _with_midpoints(keypoints[None])[0]
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


class SkeletonStage:
    """Markers -> skeleton: identification, IK, IIR low-pass, second IK."""

    def __init__(self, config: TrackerConfig | None = None) -> None:
        self.config = config or TrackerConfig()
        self.skeleton: Skeleton | None = None
        self._buffer: deque[np.ndarray] = deque(maxlen=self.config.init_frames)
        self._identify: list[np.ndarray] | None = None  # markers of the identification phase
        self._q_raw: np.ndarray | None = None
        self._q_out: np.ndarray | None = None
        self._filter = make_filter(self.config)
        # Fixed-lag mode: the smoother and the frames (stamp, weights, markers, first-IK q) it delays.
        lag = self.config.smoothing_lag_frames
        self._lag = FixedLagSmoother(smoother_model(self.config), lag) if lag > 0 else None
        self._delayed: deque[tuple[int, np.ndarray, np.ndarray, np.ndarray]] = deque(maxlen=lag + 1)
        self.status = "initializing"
        self.init_problem: str | None = None  # why the last skeleton fit failed (init_report.py)
        self._last_stamp: int | None = None
        self._joint_names = Skeleton().joint_names
        self.timings: dict[str, float] = {}
        warm_up_ik()

    @property
    def joint_names(self) -> list[str]:
        return self._joint_names

    def reset(self) -> None:
        self.skeleton = None
        self._buffer.clear()
        self._identify = None
        self._q_raw = self._q_out = None
        self._filter.reset()
        if self._lag is not None:
            self._lag.reset()
        self._delayed.clear()
        self.status = "initializing"

    def step(self, markers: Markers) -> TrackResult:
        cfg = self.config
        if markers.kind == "triangulated" and self.skeleton is not None:
            self.reset()
            self.status = "lost"
        if self.skeleton is None:
            return self._initialize(markers)
        if markers.kind != "lattice":
            return self._empty(markers, "lost")
        sk = self.skeleton
        t0 = time.perf_counter()
        dt = self._skipped_interval(markers.stamp_ns)
        rate = cfg.fps if dt is None else 1.0 / dt
        first = solve_ik(sk, self._q_raw, markers.positions, markers.weights, cfg.ik_iterations,
                         damping=cfg.ik_damping, regularization=cfg.ik_regularization,
                         prior=self._q_raw, prior_weight=cfg.ik_prior_weight * (rate / 60.0) ** 2)
        self._q_raw = first.q
        if self._identify is not None:
            return self._identifying(markers, first.keypoints)
        t1 = time.perf_counter()
        frame = (markers.stamp_ns, markers.weights.copy(), markers.positions.copy(), first.q)
        if self._lag is not None:
            smooth = self._lag(first.keypoints)
            self._delayed.append(frame)
            if smooth is None:
                return self._smoothing(markers, first.keypoints)
            frame = self._delayed[0]  # the output is the frame `lag` back
        elif isinstance(self._filter, OneEuroFilter):
            smooth = self._filter(first.keypoints, dt)
        else:
            smooth = self._filter(first.keypoints)
        t2 = time.perf_counter()
        second = solve_ik(sk, self._q_out, smooth, np.ones(N_KP), cfg.second_ik_iterations,
                          damping=cfg.ik_damping, regularization=cfg.ik_regularization)
        if second.cost > cfg.second_ik_restart_m**2:
            # The smoothed targets lie near the first IK's pose: restart from it when the
            # warm start is caught in another branch (e.g. an arm twisted at a joint limit).
            retry = solve_ik(sk, frame[3], smooth, np.ones(N_KP), cfg.second_ik_iterations,
                             damping=cfg.ik_damping, regularization=cfg.ik_regularization)
            if retry.cost < second.cost:
                second = retry
        self._q_out = second.q
        self.status = "tracking"
        angles = sk.to_angles(second.q)
        t3 = time.perf_counter()
        self.timings = {"ik": t1 - t0, "filter": t2 - t1, "ik2": t3 - t2}
        return TrackResult(frame[0], "tracking", angles, self._joint_names,
                           second.keypoints, first.keypoints, frame[1], frame[2], sk.dims.bone_lengths(), sk.dims)

    def _smoothing(self, markers: Markers, raw: np.ndarray) -> TrackResult:
        """Fixed-lag window filling: feedback, no output yet."""
        self.status = "smoothing"
        nan = np.full((N_KP, 3), np.nan)
        return TrackResult(markers.stamp_ns, "smoothing", np.full(40, np.nan), self._joint_names, nan, raw.copy(),
                           markers.weights.copy(), markers.positions.copy(), {})

    def _skipped_interval(self, stamp_ns: int) -> float | None:
        """Seconds since the previous frame set when frame sets were skipped (a graph that falls
        behind), so the prior and the filter follow the real time; None at the nominal rate."""
        last, self._last_stamp = self._last_stamp, stamp_ns
        if last is None or stamp_ns <= last:
            return None
        dt = (stamp_ns - last) / 1e9
        nominal = 1.0 / self.config.fps
        return None if abs(dt / nominal - 1.0) < 0.25 else float(min(dt, 10 * nominal))

    def _empty(self, markers: Markers, status: str) -> TrackResult:
        nan = np.full((N_KP, 3), np.nan)
        return TrackResult(markers.stamp_ns, status, np.full(40, np.nan), self._joint_names, nan, nan.copy(),
                           markers.weights.copy(), markers.positions.copy(), {})

    def _initialize(self, markers: Markers) -> TrackResult:
        cfg = self.config
        status = "lost" if self.status == "lost" else "initializing"
        self.status = "initializing"
        if markers.kind != "triangulated":
            return self._empty(markers, status)
        p = _with_midpoints(markers.positions[None])[0]
        if not all(np.isfinite(p[INDEX[n]]).all() for n in CORE + ("neck", "pelvis")):
            self._buffer.clear()  # the views must agree on consecutive frames
            return self._empty(markers, status)
        self._buffer.append(markers.positions.copy())
        if len(self._buffer) < cfg.init_frames:
            return self._empty(markers, status)
        frames = np.array(self._buffer)
        fitted = fit_skeleton(frames, cfg.init_max_fit_error_m)
        if fitted is None:
            self._buffer.popleft()
            self.init_problem = (f"the views agree, but {cfg.init_frames} frame sets of triangulated keypoints do not "
                                 f"fit one skeleton within init_max_fit_error_m = {cfg.init_max_fit_error_m:g} m")
            return self._empty(markers, status)
        self.init_problem = None
        sk, fit = fitted
        self.skeleton = sk
        self._q_raw = fit.q.copy()
        if cfg.identify_frames > 0:
            self._identify = []
            return self._identifying(markers, fit.keypoints)
        return self._start_tracking(markers, sk, fit)

    def _identifying(self, markers: Markers, raw: np.ndarray) -> TrackResult:
        """Identification phase: collect the virtual markers; once there are enough, identify
        the skeleton on all of them and start tracking (the provisional one stays otherwise)."""
        cfg = self.config
        assert self._identify is not None  # started by the first fit
        self._identify.append(np.where((markers.weights > 0)[:, None], markers.positions, np.nan))
        if len(self._identify) >= cfg.identify_frames:
            frames = np.array(self._identify)
            self._identify = None
            fitted = fit_skeleton(frames, cfg.init_max_fit_error_m, self._q_raw)
            if fitted is not None:
                return self._start_tracking(markers, *fitted)
            fit = solve_ik(self.skeleton, self._q_raw, frames[-1], np.isfinite(frames[-1]).all(axis=1).astype(float),
                           30, damping=1e-2, regularization=1e-6, line_search=True)
            return self._start_tracking(markers, self.skeleton, fit)
        self.status = "identifying"
        nan = np.full((N_KP, 3), np.nan)
        return TrackResult(markers.stamp_ns, "identifying", np.full(40, np.nan), self._joint_names, nan, raw.copy(),
                           markers.weights.copy(), markers.positions.copy(), {})

    def _start_tracking(self, markers: Markers, sk: Skeleton, fit: Any) -> TrackResult:
        self.skeleton = sk
        self._q_raw = fit.q.copy()
        self._q_out = fit.q.copy()
        self._filter.reset()
        self._filter(fit.keypoints)
        if self._lag is not None:
            self._lag.reset()
            self._delayed.clear()
            self._delayed.append((markers.stamp_ns, markers.weights.copy(), markers.positions.copy(), fit.q.copy()))
            self._lag(fit.keypoints)
            return self._smoothing(markers, fit.keypoints)
        self.status = "tracking"
        return TrackResult(markers.stamp_ns, "tracking", sk.to_angles(fit.q), self._joint_names, fit.keypoints,
                           fit.keypoints.copy(), markers.weights.copy(), markers.positions.copy(),
                           sk.dims.bone_lengths(), sk.dims)


def fit_skeleton(frames: np.ndarray, max_fit_error_m: float, q0: np.ndarray | None = None) -> tuple[Skeleton, Any] | None:
    """Identify a skeleton on keypoint frames (N, 25, 3; NaN unknown) and fit it to the last
    frame: link lengths (II-C), the waist height by the fit it gives, face/foot offsets. None
    when the fit's RMS stays above `max_fit_error_m` (the frames do not show one body)."""
    dims = identify_dimensions(frames)
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


class SpatiotemporalFilter:
    """The whole method for one person: PCMs in, skeleton out (both stages, feedback wired)."""

    def __init__(self, rig: Rig, config: TrackerConfig | None = None) -> None:
        self.config = config or TrackerConfig()
        self.rig = rig
        self.markers = MarkerStage(rig, self.config)
        self.skeleton = SkeletonStage(self.config)
        self.last: TrackResult | None = None

    def step(self, pcm: PcmViews) -> TrackResult:
        m = self.markers.step(pcm)
        r = self.skeleton.step(m)
        self.markers.feedback(r.raw_keypoints if r.status in FEEDBACK_STATUSES else None)
        self.last = r
        return r

    def tilt(self) -> np.ndarray:
        """Per-camera trunk tilt of the current skeleton (zeros while not tracking)."""
        if self.last is None or self.last.status != "tracking":
            return np.zeros(len(self.rig))
        return trunk_tilt(self.rig, self.last.keypoints)
