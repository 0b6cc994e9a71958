"""Several people in one rendered scene: the subject, rendered exactly as render_recording
renders its clip alone (body, look, room, lights), and others, each with its own clip, body
shape, size and clothes, walking along a path on the floor plan (crossing in front of the
subject from some cameras, leaving the capture volume and coming back).

The recording is render_recording's with the others added: the subject's truth stays on
TRUTH_TOPIC, person k's truth is on truth_topic(k).
"""

from __future__ import annotations

import hashlib
import itertools
import json
from dataclasses import dataclass
from pathlib import Path

import numpy as np

from ...cameras.projection import Rig
from ...errors import VmocapError
from ...keypoints import INDEX
from .body import load_body
from .recording import TRUTH_TOPIC, ClipSpec, cache_key, clip_scene, posed_bodies, prepare_motion, write_rendered
from .scene import Appearance

GROUP_VERSION = 1  # bump when a group's rendered bytes change for the same inputs
# a walker that stops and walks off another way turns on the spot at this rate (half a turn in
# 0.8 s, a brisk turn), centred on the middle of its stop: a body does not turn in one frame
TURN_RAD_S = np.pi / 0.8


def truth_topic(person: int) -> str:
    """Person `person`'s truth topic (0: the subject, on the one-person recording's topic)."""
    return TRUTH_TOPIC if person == 0 else f"/vmocap/truth/person{person}/keypoints"


@dataclass(frozen=True)
class Walker:
    """Another person: `clip` (its frames and rate must be the subject's; `variant` picks its
    body shape and look) played in place, its pelvis carried along `waypoints` ((t_s, x, y),
    linear in between, held before the first and after the last), facing where it goes, the
    whole body (and its truth) scaled by `size` about the floor."""

    clip: ClipSpec
    waypoints: tuple[tuple[float, float, float], ...]
    size: float = 1.0

    def positions(self) -> np.ndarray:
        """(T, 25, 3) keypoints along the path."""
        m = prepare_motion(self.clip)
        P = m.positions.copy()
        pelvis = P[:, INDEX["pelvis"]]
        P[..., :2] -= pelvis[:, None, :2]  # in place: the path carries the body
        left = P[:, INDEX["left_hip"]] - P[:, INDEX["right_hip"]]
        fwd = np.stack([left[:, 1], -left[:, 0]], axis=1)  # left x up: the way the hips face
        clip_yaw = float(np.arctan2(*np.nansum(fwd / np.linalg.norm(fwd, axis=1, keepdims=True), axis=0)[::-1]))
        w = np.asarray(self.waypoints, dtype=np.float64)
        if w.ndim != 2 or w.shape[1] != 3 or len(w) == 0 or np.any(np.diff(w[:, 0]) < 0):
            raise VmocapError(f"walker waypoints must be (t_s, x, y) rows in time order, got {self.waypoints}")
        t = np.arange(len(P)) / self.clip.rate_hz
        xy = np.stack([np.interp(t, w[:, 0], w[:, 1]), np.interp(t, w[:, 0], w[:, 2])], axis=1)
        heading = self._heading(t, w)
        a = heading - clip_yaw
        c, s = np.cos(a)[:, None], np.sin(a)[:, None]
        x, y = P[..., 0].copy(), P[..., 1].copy()
        P[..., 0], P[..., 1] = c * x - s * y, s * x + c * y
        P *= self.size
        P[..., :2] += xy[:, None]
        return P

    def turns(self) -> bool:
        """Whether the walker stops between two legs of different directions (and turns there)."""
        w = np.asarray(self.waypoints, dtype=np.float64)
        yaw = self._legs(w)[0]
        return bool(len(yaw) > 1 and np.any(np.abs(np.angle(np.exp(1j * np.diff(yaw)))) > 1e-9))

    @staticmethod
    def _legs(w: np.ndarray) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
        """The legs walked: (yaw, start time, end time), each (L,)."""
        step = np.diff(w[:, 1:], axis=0)
        moving = np.flatnonzero(np.linalg.norm(step, axis=1) > 1e-9)
        return np.arctan2(step[moving, 1], step[moving, 0]), w[moving, 0], w[moving + 1, 0]

    @staticmethod
    def _heading(t: np.ndarray, w: np.ndarray) -> np.ndarray:
        """(T,) direction of travel; while standing between two legs, turning from the one to the
        other at TURN_RAD_S, centred on the middle of the stop (the whole stop if shorter)."""
        yaw, start, end = Walker._legs(w)
        if yaw.size == 0:
            return np.zeros(len(t))  # standing all along: facing +x
        heading = np.full(len(t), yaw[0])
        for k in range(len(yaw)):
            heading[t >= start[k]] = yaw[k]
            if k + 1 < len(yaw):  # the stop after leg k: turn towards leg k + 1
                delta = float(np.angle(np.exp(1j * (yaw[k + 1] - yaw[k]))))  # the shorter way round
                stop = start[k + 1] - end[k]
                span = min(abs(delta) / TURN_RAD_S, stop)
                t0 = end[k] + 0.5 * (stop - span)
                f = np.clip((t - t0) / span, 0.0, 1.0) if span > 0 else (t >= t0).astype(float)
                during = (t > end[k]) & (t < start[k + 1])
                heading[during] = yaw[k] + delta * f[during]
        return heading


@dataclass(frozen=True)
class GroupSpec:
    """The subject's clip and the people walking around it."""

    subject: ClipSpec
    others: tuple[Walker, ...]

    def label(self) -> str:
        return f"{self.subject.label()}+{len(self.others)}"


def group_cache_key(spec: GroupSpec, rig: Rig) -> str:
    h = hashlib.sha256(cache_key(spec.subject, rig).encode())
    for w in spec.others:
        h.update(Path(w.clip.path).read_bytes())
        h.update(json.dumps({"frames": w.clip.frames, "rate": w.clip.rate_hz, "seed": w.clip.seed, "variant": w.clip.variant,
                             "waypoints": [list(p) for p in w.waypoints], "size": w.size, "v": GROUP_VERSION,
                             **({"turn_rad_s": TURN_RAD_S} if w.turns() else {})}).encode())
    return h.hexdigest()[:16]


def render_group(spec: GroupSpec, rig: Rig, cache_dir: Path, progress: bool = True) -> Path:
    """Render (or find in the cache) the recording of the subject with the others; its path."""
    for w in spec.others:
        if (w.clip.frames, w.clip.rate_hz) != (spec.subject.frames, spec.subject.rate_hz):
            raise VmocapError(f"{w.clip.label()}: {w.clip.frames} frames at {w.clip.rate_hz} Hz, the subject has "
                              f"{spec.subject.frames} at {spec.subject.rate_hz} Hz")
    cache_dir.mkdir(parents=True, exist_ok=True)
    out = cache_dir / f"{spec.label()}_{group_cache_key(spec, rig)}.mcap"
    if out.exists():
        return out
    motion, posed, scene = clip_scene(spec.subject, rig)
    truths = [(TRUTH_TOPIC, motion.positions)]
    walkers = []
    for k, w in enumerate(spec.others, start=1):
        P = w.positions()
        body = load_body(w.clip.shape())
        scene.add_person(body, Appearance.draw(np.random.default_rng(w.clip.rng_seed())), w.clip.rng_seed())
        walkers.append(posed_bodies(body, P))
        truths.append((truth_topic(k), P))

    def frames():
        others = zip(*[p() for p in walkers]) if walkers else itertools.repeat(())
        return zip(posed(), others)

    scene.fit_box(np.concatenate([v, *o]) for v, o in frames())
    write_rendered(out, scene, frames(), spec.subject.rate_hz, truths, spec.label(), progress)
    return out
