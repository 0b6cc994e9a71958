"""One pipeline per person (our extension; the paper tracks one person): each lattice search
sees PCMs rendered only from the 2D detections assigned to its own person (people.py), so it
searches near its own person; new people are started when they appear, trackers whose person
left all views are ended. Nothing here reads ground truth.
"""

from __future__ import annotations

from dataclasses import dataclass, field
from typing import Any, Callable, Sequence

import numpy as np
from scipy.optimize import linear_sum_assignment

from ..cameras.projection import Rig
from ..keypoints import INDEX
from .people import N_KP, PcmRenderer, associate
from .triangulation import triangulate_robust


@dataclass
class MultiPersonConfig:
    gate_px: float = 40.0  # a 2D person joins a track when its mean distance to the
    gate_rel: float = 0.35  # projected track is < max(gate_px, gate_rel * projected height)
    max_epipolar_px: float = 30.0  # cross-view association of unexplained 2D people
    new_min_views: int = 2  # a new person needs this many views ...
    new_min_joints: int = 10  # ... and this many triangulated keypoints, torso included
    new_max_residual_px: float = 15.0  # median reprojection residual of a new person
    min_views: int = 2  # a track with fewer assigned views this frame is "unseen"
    max_unseen: int = 8  # frames a track survives unseen before it ends
    duplicate_m: float = 0.25  # two tracks closer than this (mean keypoint distance) merge
    joint_gate_m: float | None = 0.25  # per-keypoint gate around a tracked person (None: off)


@dataclass
class Track:
    track_id: int
    filter: Any  # a method.pipeline.Pipeline (anything with .step(PcmViews).skeleton -> TrackResult)
    keypoints: np.ndarray  # (25, 3) last feedback keypoints (NaN before the first result)
    born: int
    unseen: int = 0
    members: dict[int, list[int]] = field(default_factory=dict)  # camera -> 2D people indices
    result: object = None  # the filter's last TrackResult (None when not stepped)
    output: np.ndarray | None = None  # (25, 3) this frame's reconstruction, None when unseen
    source: str = "none"  # "tracker" | "triangulated" (while initializing) | "unseen"


_TORSO = np.array([INDEX[n] for n in ("neck", "left_shoulder", "right_shoulder", "left_hip", "right_hip")])
_HEIGHT_PAIRS = (INDEX["neck"], INDEX["pelvis"])


def _projected_cost(uv_track: np.ndarray, ok_track: np.ndarray, people: np.ndarray) -> np.ndarray:
    """Mean pixel distance between projected tracks (T, 25, 2) and 2D people (P, 25, 3)."""
    d = np.linalg.norm(uv_track[:, None] - people[None, :, :, :2], axis=-1)  # (T, P, 25)
    both = ok_track[:, None, :] & (people[None, :, :, 2] > 0)
    n = both.sum(axis=-1)
    cost = np.where(both, d, 0.0).sum(axis=-1) / np.maximum(n, 1)
    return np.where(n >= 3, cost, np.inf)


class MultiPersonTracker:
    """One lattice filter per person, fed with PCMs of that person's own detections.

    `make_filter()` returns a fresh single-person pipeline (method.pipeline.Pipeline).
    `step(people, stamp_ns)` takes the 2D people of each view ((P_c, 25, 3): u, v, score) and
    returns the active tracks after this frame.
    """

    def __init__(self, rig: Rig, renderer: PcmRenderer, make_filter: Callable[[], object], config: MultiPersonConfig | None = None) -> None:
        self.rig = rig
        self.renderer = renderer
        self.make_filter = make_filter
        self.cfg = config or MultiPersonConfig()
        self.tracks: list[Track] = []
        self._next_id = 0
        self.frame = 0
        self.events: list[tuple[int, str, int]] = []  # (frame, "start" | "end", track id)

    # ---- assignment of 2D people to existing tracks
    def _assign(self, people: Sequence[np.ndarray]) -> list[np.ndarray]:
        """Give each track its 2D people per view; returns per view the mask of used people."""
        used = [np.zeros(len(p), dtype=bool) for p in people]
        for t in self.tracks:
            t.members = {}
        live = [t for t in self.tracks if np.isfinite(t.keypoints).any()]
        if not live:
            return used
        kp = np.array([t.keypoints for t in live])  # (T, 25, 3)
        finite = np.isfinite(kp).all(axis=-1)
        uv, front = self.rig.project(np.nan_to_num(kp))  # (C, T, 25, 2)
        ok = finite[None] & front
        h = np.linalg.norm(uv[:, :, _HEIGHT_PAIRS[0]] - uv[:, :, _HEIGHT_PAIRS[1]], axis=-1)  # (C, T)
        gate = np.maximum(self.cfg.gate_px, self.cfg.gate_rel * np.nan_to_num(h))
        for c, pc in enumerate(people):
            if len(pc) == 0:
                continue
            cost = _projected_cost(uv[c], ok[c], pc)  # (T, P)
            cost = np.where(cost <= gate[c][:, None], cost, np.inf)
            if not np.isfinite(cost).any():
                continue
            rows, cols = linear_sum_assignment(np.where(np.isfinite(cost), cost, 1e9))
            for r, q in zip(rows, cols):
                if np.isfinite(cost[r, q]):
                    live[r].members[c] = [int(q)]
                    used[c][q] = True
            # Fragments of a person the PAF grouping split: join the track they are near when
            # they add joints it does not have in this view.
            for q in np.nonzero(~used[c])[0]:
                r = int(np.argmin(cost[:, q]))
                if not np.isfinite(cost[r, q]) or c not in live[r].members:
                    continue
                have = np.zeros(N_KP, dtype=bool)
                for q2 in live[r].members[c]:
                    have |= pc[q2, :, 2] > 0
                if not (have & (pc[q, :, 2] > 0)).any():
                    live[r].members[c].append(int(q))
                    used[c][q] = True
        return used

    def _observations(self, people: Sequence[np.ndarray], members: dict[int, list[int]]) -> tuple[np.ndarray, np.ndarray]:
        uv = np.zeros((len(self.rig), N_KP, 2))
        w = np.zeros((len(self.rig), N_KP))
        for c, qs in members.items():
            for q in qs:
                sel = people[c][q, :, 2] > 0
                uv[c, sel] = people[c][q, sel, :2]
                w[c, sel] = people[c][q, sel, 2]
        return uv, w

    def _gate_joints(self, keypoints: np.ndarray, uv: np.ndarray, w: np.ndarray) -> np.ndarray:
        """Drop single detections further than `joint_gate_m` (converted to pixels at the
        keypoint's depth) from the tracked person's projected keypoint: a wrist of someone
        else that the 2D grouping attached to this person must not pull its filter."""
        finite = np.isfinite(keypoints).all(axis=-1)
        proj, front = self.rig.project(np.nan_to_num(keypoints))  # (C, 25, 2)
        depth = self.rig.to_camera_frames(np.nan_to_num(keypoints))[..., 2]  # (C, 25)
        focal = np.array([c.K[0, 0] for c in self.rig])[:, None]
        gate = self.cfg.joint_gate_m * focal / np.maximum(depth, 0.1)
        far = np.linalg.norm(uv - proj, axis=-1) > gate
        return np.where(far & front & finite[None] & (w > 0), 0.0, w)

    # ---- new people
    def _start_new(self, people: Sequence[np.ndarray], used: list[np.ndarray]) -> None:
        rest = [p[~u] for p, u in zip(people, used)]
        index = [np.nonzero(~u)[0] for u in used]
        cfg = self.cfg
        for person in associate(self.rig, rest, cfg.max_epipolar_px, cfg.new_min_views):
            pts = person.keypoints
            good = np.isfinite(pts).all(axis=1) & (np.nan_to_num(person.residual_px, nan=1e9) < 2 * cfg.new_max_residual_px)
            if good.sum() < cfg.new_min_joints or good[_TORSO].sum() < 4:
                continue
            if np.nanmedian(person.residual_px) > cfg.new_max_residual_px:
                continue
            if any(self._distance(pts, t.keypoints) < 2 * cfg.duplicate_m for t in self.tracks):
                continue
            t = Track(self._next_id, self.make_filter(), np.full((N_KP, 3), np.nan), born=self.frame)
            t.members = {c: [int(index[c][i])] for c, i in person.members.items()}
            self._next_id += 1
            self.tracks.append(t)
            self.events.append((self.frame, "start", t.track_id))

    @staticmethod
    def _distance(a: np.ndarray, b: np.ndarray) -> float:
        d = np.linalg.norm(a - b, axis=-1)
        return float(np.nanmean(d)) if np.isfinite(d).any() else np.inf

    def _end(self, t: Track) -> None:
        self.tracks.remove(t)
        self.events.append((self.frame, "end", t.track_id))

    def step(self, people: Sequence[np.ndarray], stamp_ns: int = 0) -> list[Track]:
        cfg = self.cfg
        used = self._assign(people)
        self._start_new(people, used)
        for t in list(self.tracks):
            uv, w = self._observations(people, t.members)
            if cfg.joint_gate_m and t.source == "tracker":
                w = self._gate_joints(t.keypoints, uv, w)
            n_views = int((w.max(axis=1) > 0).sum())
            if n_views < cfg.min_views:
                t.unseen += 1
                if t.unseen > cfg.max_unseen:
                    self._end(t)
                else:
                    t.result = None  # not stepped: the filter keeps its state for a return
                t.output, t.source = None, "unseen"
                continue
            t.unseen = 0
            pcm = self.renderer.render(uv, w, w.max(axis=1) > 0, stamp_ns)
            res = t.filter.step(pcm).skeleton
            t.result = res
            out = np.asarray(getattr(res, "keypoints", np.full((N_KP, 3), np.nan)), dtype=np.float64)
            raw = np.asarray(getattr(res, "raw_keypoints", out), dtype=np.float64)
            if getattr(res, "status", "tracking") == "tracking" and np.isfinite(out).all():
                t.output, t.source, t.keypoints = out.copy(), "tracker", raw.copy()
            else:
                # Initializing (the filter needs a few agreeing frames) or re-initializing:
                # report and gate with the triangulation of the person's own detections.
                pts, _ = triangulate_robust(self.rig, uv, w)
                t.output, t.source, t.keypoints = pts, "triangulated", pts.copy()
        # Two filters that converged onto one person: keep the older.
        for a in list(self.tracks):
            for b in list(self.tracks):
                if a is not b and a in self.tracks and b in self.tracks and a.born <= b.born:
                    if self._distance(a.keypoints, b.keypoints) < cfg.duplicate_m:
                        self._end(b)
        self.frame += 1
        return list(self.tracks)
