"""Is the body the track comes back to still the subject? The path gate.

While the images disagree with the skeleton ("uncertain", consistency.py) the track goes on:
the lattice search follows whatever peaks lie near the fed-back skeleton and the crops follow
the track. Beside another person (shoulder to shoulder, a hug, a hand-over) those peaks can be
the other body's: the track slides onto it, the images agree again, and without this gate it
would resume as "tracking" on the wrong person. A person does not jump: where the subject
can be when the images agree again follows from where its hip centre was heading on the
last frame sets the images confirmed. A walker keeps going or stops (in front of someone: face
to face, a hand-over), so the subject can be anywhere from where it was last confirmed to where
its velocity carries it: a track that comes back farther than `max_m` from that stretch (more
when those frame sets are old: `bound`) has left the subject: the skeleton stage starts over,
and the detector looks for the subject at the expected place (`expected`), not where the track
went.

Only the horizontal place counts (world Z is up): another body stands beside the subject, and
the subject's own hip centre moves fast vertically (a jump, a fall, a backflip, getting up),
where a velocity carried on would miss by 0.5 g t^2.
"""

from __future__ import annotations

from collections import deque

import numpy as np

# The confirmed points the expectation is drawn from: this long before the last one.
WINDOW_S = 0.25
# Before the views disagreed, a slide onto another body pulled the confirmed hip centre 50 mm
# towards it over up to 8 frame sets (0.13 s at 60 Hz, the beside scene): the last 0.1 s are
# dropped, the medians bear the rest.
SUSPECT_S = 0.1
# Past the horizon the subject may have turned or stopped: the place it can be grows at a brisk
# walk's speed. A track dropped for over a second (an overloaded graph keeps few frame sets)
# comes back anywhere a walker reaches, so there the gate holds little back.
WANDER_MPS = 1.5


class PathGate:
    """The confirmed hip-centre path of one track: `add` on every frame set output as
    "tracking", `doubt` when the images stop agreeing, `strayed` when a track comes back
    from "uncertain"."""

    def __init__(self, max_m: float, horizon_s: float, window_s: float = WINDOW_S, suspect_s: float = SUSPECT_S) -> None:
        self.max_m = float(max_m)  # 0: never stray (the gate is off)
        self.horizon_s = float(horizon_s)  # the confirmed velocity is carried this long at most
        self.window_s = float(window_s)
        self.suspect_s = float(suspect_s)
        self._path: deque[tuple[int, np.ndarray]] = deque()

    def reset(self) -> None:
        self._path.clear()

    def add(self, stamp_ns: int, pelvis: np.ndarray) -> None:
        if np.isfinite(pelvis).all():
            self._path.append((int(stamp_ns), np.asarray(pelvis, dtype=np.float64).copy()))
            while len(self._path) > 2 and (stamp_ns - self._path[0][0]) * 1e-9 > self.window_s:
                self._path.popleft()

    def doubt(self, stamp_ns: int) -> None:
        """The images disagree from this frame set on: the confirmed points of the last
        suspect_s before it are no longer trusted (at least two points stay). The check reads
        the skeleton fed back, one frame set late, and a track sliding onto another body is
        pulled towards it over a few frame sets before the views disagree: kept, those points
        bend the expected path towards the other body."""
        while len(self._path) > 2 and (stamp_ns - self._path[-1][0]) * 1e-9 < self.suspect_s:
            self._path.pop()

    def expected(self, stamp_ns: int) -> np.ndarray | None:
        """Where the hip centre is heading at stamp_ns: the last confirmed one moved on
        horizontally with the velocity over the confirmed window, for horizon_s at most (a
        walker keeps going, nobody keeps a velocity for long); None before any confirmed
        frame set."""
        reach = self._reach(stamp_ns)
        return None if reach is None else reach[1]

    def _reach(self, stamp_ns: int) -> tuple[np.ndarray, np.ndarray] | None:
        """Where the hip centre is if the subject stopped at the last confirmed frame set, and
        where it is if it kept going until stamp_ns (`expected`); None before any confirmed
        frame set."""
        if not self._path:
            return None
        t1, p1 = self._path[-1]
        if len(self._path) < 2:
            return p1.copy(), p1.copy()
        t = np.array([s for s, _ in self._path], dtype=np.float64) * 1e-9
        p = np.array([q for _, q in self._path])
        # Medians of the steps and of the points moved on: the first frame sets of a slide onto
        # another body are often still confirmed (the check reads the previous skeleton), and
        # the last point or step alone would carry the expectation towards that body.
        velocity = np.median(np.diff(p, axis=0) / np.maximum(np.diff(t), 1e-3)[:, None], axis=0)
        velocity[2] = 0.0
        ahead = t[-1] - t
        stopped = np.median(p + ahead[:, None] * velocity, axis=0)
        ahead = ahead + min(max((stamp_ns - t1) * 1e-9, 0.0), self.horizon_s)
        return stopped, np.median(p + ahead[:, None] * velocity, axis=0)

    def bound(self, stamp_ns: int) -> float:
        """How far from the expected place the subject can be at stamp_ns: max_m, growing at
        WANDER_MPS once the last confirmed point is more than horizon_s old."""
        if not self._path:
            return self.max_m
        late = (stamp_ns - self._path[-1][0]) * 1e-9 - self.horizon_s
        return self.max_m + WANDER_MPS * max(late, 0.0)

    def strayed(self, stamp_ns: int, pelvis: np.ndarray) -> np.ndarray | None:
        """Where the subject was heading, when the hip centre lies horizontally farther than
        `bound` from the stretch between stopping and keeping going (the track has left the
        subject); None otherwise."""
        if self.max_m <= 0 or not np.isfinite(pelvis).all():
            return None
        reach = self._reach(stamp_ns)
        if reach is None:
            return None
        stopped, exp = reach
        a, d = stopped[:2], exp[:2] - stopped[:2]
        x = np.asarray(pelvis, dtype=np.float64)[:2] - a
        s = float(np.clip((x @ d) / (d @ d), 0.0, 1.0)) if d @ d > 0 else 0.0
        if np.linalg.norm(x - s * d) <= self.bound(stamp_ns):
            return None
        return exp
