"""The marker stage (paper II-C, II-D): PCMs -> virtual markers.

While nobody is tracked, the markers are the triangulated PCM centroids (init.py); while
tracking, the lattice search (lattice.py, eq. 1-2) around the skeleton fed back from the
previous frame, refined by the views' own peaks (refinement.py). A keypoint weak for a few
frames is searched again at its PCM peaks; a person whose markers stay weak is lost and the
stage starts over from triangulation. The skeleton fed back is checked against the PCMs of
its own frame set (consistency.py), and the next markers carry that check to the skeleton stage.
"""

from __future__ import annotations

import dataclasses
import time

import numpy as np

from ..cameras.projection import Rig
from ..pcm.views import PcmViews
from .config import MarkersConfig
from .consistency import ViewCheck, check_views
from .init import triangulated_markers
from .init_report import camera_mask
from .lattice import PcmSampler, lattice_search
from .lattice import warm_up as warm_up_lattice
from .mirror import swapped_groups, unmirrored
from .occlusion import outside_images, without_hidden
from .refinement import refine_markers
from .refinement import warm_up as warm_up_refinement
from .results import N_KP, Markers, nan_markers, skeleton_of
from .triangulation import triangulate_robust


class MarkerStage:
    """PCMs -> virtual markers (triangulated centroids while initializing, lattice search while
    tracking)."""

    def __init__(self, rig: Rig, config: MarkersConfig | None = None) -> None:
        self.rig = rig
        self.config = config or MarkersConfig()
        self.centres: np.ndarray | None = None  # skeleton keypoints of the previous frame
        self.velocity = np.zeros((N_KP, 3))
        self._low = 0
        self._weak = np.zeros(N_KP, dtype=np.int64)  # consecutive weak frames per keypoint
        self.timings: dict[str, float] = {}  # seconds spent in the last step, per stage
        # the last frame set's PCMs (and its sampler), which the skeleton fed back is checked against
        self._last: tuple[PcmViews, PcmSampler | None] | None = None
        self._check: ViewCheck | None = None
        warm_up_lattice(rig)
        warm_up_refinement(rig)

    @property
    def tracking(self) -> bool:
        return self.centres is not None

    def feedback(self, keypoints: np.ndarray | None) -> None:
        """The first-IK keypoints of the frame just processed, or None (or a seed) when not tracking."""
        keypoints = skeleton_of(keypoints)
        if keypoints is None:
            self.centres = None
            self.velocity[:] = 0.0
            self._weak[:] = 0
            self._check = None
            return
        kp = np.asarray(keypoints, dtype=np.float64)
        if self._last is not None:
            self._check = check_views(self.rig, self._last[0], kp, self._last[1])
        if self.centres is not None:
            self.velocity = kp - self.centres
        else:
            self.velocity[:] = 0.0
        self.centres = kp.copy()

    def step(self, pcm: PcmViews) -> Markers:
        t0 = time.perf_counter()
        check, self._check, self._last = self._check, None, None
        if pcm.n_views == 0:
            out = nan_markers(pcm.stamp_ns)
        elif self.centres is None:
            out = triangulated_markers(self.rig, pcm.sanitized(), self.config)
            self._last = (pcm, None)
        else:
            out = self._lattice(pcm)  # the lattice search sanitizes the values it reads
        out.check = check if out.kind == "lattice" else None
        out.others, out.person = pcm.others, pcm.person
        self.timings = {"lattice": time.perf_counter() - t0}
        return out

    def _lattice(self, pcm: PcmViews) -> Markers:
        cfg = self.config
        centres = self.centres
        assert centres is not None  # set by the previous frame's skeleton (markers run only while tracking)
        if cfg.prediction == "constant_velocity":
            centres = centres + self.velocity
        # A keypoint predicted outside a camera's image: that view's map holds the landmark
        # model's guess from the rest of the body, not a sighting; the views that see it decide.
        outside = outside_images(self.rig, centres[None])[0]
        pcm = without_hidden(pcm, outside)
        sampler = PcmSampler(self.rig, pcm)  # one per frame: the lattice search, the refinement, the check
        mirrored = 0
        if cfg.unmirror_ratio > 0:
            swap = swapped_groups(self.rig, pcm, centres, cfg.unmirror_ratio, cfg.unmirror_min_value, sampler)
            if swap.any():
                mirrored = int(np.bitwise_or.reduce(np.left_shift(1, pcm.camera[swap.any(axis=1)])))
                pcm = unmirrored(pcm, swap)
                sampler = PcmSampler(self.rig, pcm)
        self._last = (pcm, sampler)
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
        out = nan_markers(pcm.stamp_ns, "lattice")
        out.mirrored = mirrored
        out.positions[pcm.keypoints] = markers
        out.weights[pcm.keypoints] = np.where(seen, weights, 0.0)
        # the cameras whose maps confirm each marker: this frame set's own evidence (Markers.support)
        out.cameras = check_views(self.rig, pcm, out.positions, sampler).agree
        # the views that can weigh each marker, whatever the CNN made of them (WeightTrend)
        viewed = np.zeros(len(self.rig), dtype=bool)
        viewed[np.asarray(pcm.camera, dtype=np.intp)] = True
        out.inside = camera_mask(viewed[:, None] & ~outside)
        n_cam = max(len(np.unique(pcm.camera[pcm.valid.any(axis=1)])), 1)
        observed = max(int(pcm.valid.any(axis=0).sum()), 1)
        out.score = float(out.weights.sum() / (n_cam * observed))
        self._low = self._low + 1 if out.score < cfg.lost_score else 0
        if self._low >= cfg.lost_frames:
            # Lost: start over from triangulation with this very frame.
            self._low = 0
            self.feedback(None)
            return triangulated_markers(self.rig, pcm.sanitized(), self.config)
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
        masked = dataclasses.replace(pcm, valid=only)
        alt = lattice_search(self.rig, masked, centres, k=1, spacing=cfg.lattice_spacing, subcell=cfg.subcell)
        alt.markers, alt.weights, alt.n_views = alt.markers[cand], alt.weights[cand], alt.n_views[cand]
        better = alt.weights > weights[cand]
        markers, weights, n_views = markers.copy(), weights.copy(), n_views.copy()
        markers[cand[better]] = alt.markers[better]
        weights[cand[better]] = alt.weights[better]
        n_views[cand[better]] = alt.n_views[better]
        return markers, weights, n_views
