"""Several people from 2D detections (our extension for the Shelf benchmark; the paper tracks
one person): the look that people_tracker.py runs instead of the CNN's (people_look.py), with
the same stages per person after it. Each person's heatmaps are rendered from the 2D detections
assigned to them alone (people.py), so each lattice search searches near its own person.

Per frame set: the 2D people of each view go to the tracked person whose projected skeleton
they fit (Hungarian assignment, gated in pixels); the rest are associated across views
(epipolar consistency, triangulation) into new people. A person seen by fewer than
`min_views` views is not stepped (their stages keep their state for a return); until their
skeleton is fed back they are where their own detections triangulate. Nothing here reads
ground truth.
"""

from __future__ import annotations

import dataclasses
from dataclasses import dataclass, field
from typing import Sequence

import numpy as np
from scipy.optimize import linear_sum_assignment

from ..cameras.projection import Rig
from ..keypoints import INDEX
from .people import N_KP, PcmRenderer, associate
from .people_config import PeopleConfig, ended_people
from .people_look import Look
from .results import skeleton_of
from .triangulation import triangulate_robust


@dataclass
class MultiPersonConfig:
    gate_px: float = 40.0  # a 2D person joins a track when its mean distance to the
    gate_rel: float = 0.35  # projected track is < max(gate_px, gate_rel * projected height)
    max_epipolar_px: float = 30.0  # cross-view association of unexplained 2D people
    new_min_views: int = 2  # a new person needs this many views ...
    new_min_joints: int = 10  # ... and this many triangulated keypoints, torso included
    new_max_residual_px: float = 15.0  # median reprojection residual of a new person
    min_views: int = 2  # a person with fewer assigned views in a frame set is not stepped
    duplicate_m: float = 0.25  # a new person this close to a tracked one (mean keypoint distance, x2) is them
    joint_gate_m: float | None = 0.25  # per-keypoint gate around a tracked person (None: off)


@dataclass
class Seat:
    """A person as the detections' look knows them (people_look.Seat's counterpart)."""

    number: int
    slot: int
    keypoints: np.ndarray  # (25, 3): their fed-back skeleton, else the triangulation of their detections
    seen_ns: int
    tracked: bool = False  # a skeleton was fed back for the last frame set they were stepped in
    members: dict[int, list[int]] = field(default_factory=dict)  # camera -> their 2D people in it
    triangulated: np.ndarray | None = None  # (25, 3) their detections triangulated, this frame set (None: not stepped)


_TORSO = np.array([INDEX[n] for n in ("neck", "left_shoulder", "right_shoulder", "left_hip", "right_hip")])
_HEIGHT_PAIRS = (INDEX["neck"], INDEX["pelvis"])


def _projected_cost(uv_track: np.ndarray, ok_track: np.ndarray, people: np.ndarray) -> np.ndarray:
    """Mean pixel distance between projected tracks (T, 25, 2) and 2D people (P, 25, 3)."""
    d = np.linalg.norm(uv_track[:, None] - people[None, :, :, :2], axis=-1)  # (T, P, 25)
    both = ok_track[:, None, :] & (people[None, :, :, 2] > 0)
    n = both.sum(axis=-1)
    cost = np.where(both, d, 0.0).sum(axis=-1) / np.maximum(n, 1)
    return np.where(n >= 3, cost, np.inf)


def _distance(a: np.ndarray, b: np.ndarray) -> float:
    d = np.linalg.norm(a - b, axis=-1)
    return float(np.nanmean(d)) if np.isfinite(d).any() else np.inf


class DetectionsLook:
    """People from the 2D people of each view ((P_c, 25, 3): u, v, score), each person's
    heatmaps rendered from their own detections (module doc). The interface of
    people_look.PeopleLook: `step`, `feedback`, `ended`, `end`."""

    own_maps = True  # each person's maps hold their own detections alone (MarkerSlot may re-acquire)

    def __init__(self, rig: Rig, renderer: PcmRenderer, config: MultiPersonConfig | None = None,
                 people: PeopleConfig | None = None) -> None:
        self.rig, self.renderer = rig, renderer
        self.cfg = config or MultiPersonConfig()
        self.config = people or PeopleConfig()
        self.seats: list[Seat] = []
        self._next = 0

    # ---- assignment of 2D people to the people tracked
    def _assign(self, people: Sequence[np.ndarray]) -> list[np.ndarray]:
        """Give each person their 2D people per view; returns per view the mask of used people."""
        used = [np.zeros(len(p), dtype=bool) for p in people]
        for s in self.seats:
            s.members = {}
        live = [s for s in self.seats if np.isfinite(s.keypoints).any()]
        if not live:
            return used
        kp = np.array([s.keypoints for s in live])  # (T, 25, 3)
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
            # Fragments of a person the PAF grouping split: join the person they are near when
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
        else that the 2D grouping attached to this person must not pull their stages."""
        assert self.cfg.joint_gate_m is not None  # called only with the gate on
        finite = np.isfinite(keypoints).all(axis=-1)
        proj, front = self.rig.project(np.nan_to_num(keypoints))  # (C, 25, 2)
        depth = self.rig.to_camera_frames(np.nan_to_num(keypoints))[..., 2]  # (C, 25)
        focal = np.array([c.K[0, 0] for c in self.rig])[:, None]
        gate = self.cfg.joint_gate_m * focal / np.maximum(depth, 0.1)
        far = np.linalg.norm(uv - proj, axis=-1) > gate
        return np.where(far & front & finite[None] & (w > 0), 0.0, w)

    # ---- new people
    def _start_new(self, people: Sequence[np.ndarray], used: list[np.ndarray], stamp_ns: int) -> int:
        """New people from the 2D people nobody took; returns how many were left out for want of a slot."""
        rest = [p[~u] for p, u in zip(people, used)]
        index = [np.nonzero(~u)[0] for u in used]
        cfg = self.cfg
        left_out = 0
        for person in associate(self.rig, rest, cfg.max_epipolar_px, cfg.new_min_views):
            pts = person.keypoints
            good = np.isfinite(pts).all(axis=1) & (np.nan_to_num(person.residual_px, nan=1e9) < 2 * cfg.new_max_residual_px)
            if good.sum() < cfg.new_min_joints or good[_TORSO].sum() < 4:
                continue
            if np.nanmedian(person.residual_px) > cfg.new_max_residual_px:
                continue
            if any(_distance(pts, s.keypoints) < 2 * cfg.duplicate_m for s in self.seats):
                continue
            taken = {s.slot for s in self.seats}
            slot = next((k for k in range(self.config.max_people) if k not in taken), None)
            if slot is None:
                left_out += 1
                continue
            s = Seat(self._next, slot, np.full((N_KP, 3), np.nan), stamp_ns)
            s.members = {c: [int(index[c][i])] for c, i in person.members.items()}
            self._next += 1
            self.seats.append(s)
        return left_out

    def step(self, people: Sequence[np.ndarray], stamp_ns: int) -> Look:
        cfg = self.cfg
        used = self._assign(people)
        left_out = self._start_new(people, used, stamp_ns)
        views = {}
        for s in self.seats:
            uv, w = self._observations(people, s.members)
            if cfg.joint_gate_m and s.tracked:
                w = self._gate_joints(s.keypoints, uv, w)
            seen = w.max(axis=1) > 0
            s.triangulated = None
            if seen.sum() < cfg.min_views:
                continue  # not stepped: their stages keep their state for a return
            views[s.number] = dataclasses.replace(self.renderer.render(uv, w, seen, stamp_ns), person=s.number)
            # until a skeleton is fed back, where their own detections triangulate
            s.triangulated = triangulate_robust(self.rig, uv, w)[0]
            s.keypoints, s.tracked = s.triangulated.copy(), False
        untracked = np.array([int((~u).sum()) for u in used])
        return Look(stamp_ns, views, {s.number: s.slot for s in self.seats}, untracked, left_out)

    def feedback(self, number: int, stamp_ns: int, feedback: np.ndarray | None, tracking: bool = True) -> None:
        """A person's fed-back skeleton: where their detections are looked for next once it is
        output (`tracking`); before, and while it is held back, where they triangulate (a
        skeleton the images disagree with must not pull the detections it is given)."""
        seat = next((s for s in self.seats if s.number == number), None)
        body = skeleton_of(feedback)
        if seat is not None and body is not None and tracking:
            seat.keypoints, seat.tracked, seat.seen_ns = np.array(body, dtype=np.float64), True, stamp_ns

    def ended(self, stamp_ns: int) -> set[int]:
        """The people who end at `stamp_ns` by what was fed back (people_config.ended_people)."""
        gone, merged = ended_people(stamp_ns, {s.number: s.seen_ns for s in self.seats},
                                    {s.number: s.keypoints if s.tracked else None for s in self.seats}, self.config)
        return gone | merged

    def end(self, numbers: Sequence[int] | set[int]) -> None:
        self.seats = [s for s in self.seats if s.number not in numbers]
