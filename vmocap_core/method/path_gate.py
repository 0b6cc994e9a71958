"""Is the body the track comes back to still the subject? The path gate.

While the images disagree with the skeleton ("uncertain", consistency.py) the track goes on:
the lattice search follows whatever peaks lie near the fed-back skeleton and the crops follow
the track. Beside another person (shoulder to shoulder, a hug, a hand-over) those peaks can be
the other body's: the track slides onto it, the images agree again, and without this gate it
would resume as "tracking" on the wrong person. A person does not jump: where the subject
can be when the images agree again follows from where its hip centre was heading on the
last frame sets the images confirmed. A track that comes back farther than `max_m` from that
has left the subject: the skeleton stage starts over, and the detector looks for the subject
at the expected place (`expected`), not where the track went.
"""

from __future__ import annotations

from collections import deque

import numpy as np


class PathGate:
    """The confirmed hip-centre path of one track: `add` on every frame set output as
    "tracking", `strayed` when a track comes back from "uncertain"."""

    def __init__(self, max_m: float, horizon_s: float, window: int = 10) -> None:
        self.max_m = float(max_m)  # 0: never stray (the gate is off)
        self.horizon_s = float(horizon_s)  # the confirmed velocity is carried this long at most
        self._path: deque[tuple[int, np.ndarray]] = deque(maxlen=max(int(window), 2))

    def reset(self) -> None:
        self._path.clear()

    def add(self, stamp_ns: int, pelvis: np.ndarray) -> None:
        if np.isfinite(pelvis).all():
            self._path.append((int(stamp_ns), np.asarray(pelvis, dtype=np.float64).copy()))

    def expected(self, stamp_ns: int) -> np.ndarray | None:
        """Where the hip centre is heading at stamp_ns: the last confirmed one moved on with
        the velocity over the confirmed window, for horizon_s at most (a walker keeps going,
        nobody keeps a velocity for long); None before any confirmed frame set."""
        if not self._path:
            return None
        t1, p1 = self._path[-1]
        if len(self._path) < 2:
            return p1.copy()
        t = np.array([s for s, _ in self._path], dtype=np.float64) * 1e-9
        p = np.array([q for _, q in self._path])
        # Medians of the steps and of the points moved on: the first frame sets of a slide onto
        # another body are often still confirmed (the check reads the previous skeleton), and
        # the last point or step alone would carry the expectation towards that body.
        velocity = np.median(np.diff(p, axis=0) / np.maximum(np.diff(t), 1e-3)[:, None], axis=0)
        ahead = t[-1] - t + min(max((stamp_ns - t1) * 1e-9, 0.0), self.horizon_s)
        return np.median(p + ahead[:, None] * velocity, axis=0)

    def strayed(self, stamp_ns: int, pelvis: np.ndarray) -> np.ndarray | None:
        """Where the subject was heading, when the hip centre lies farther than max_m from it
        (the track has left the subject); None otherwise."""
        if self.max_m <= 0 or not np.isfinite(pelvis).all():
            return None
        exp = self.expected(stamp_ns)
        return exp if exp is not None and np.linalg.norm(np.asarray(pelvis) - exp) > self.max_m else None
