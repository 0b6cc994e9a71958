"""Mapping a camera's own clock to ROS (host) time: estimated offset, tracked drift.

Each frame gives a pair (device stamp, host arrival time). Arrival = exposure + transfer and
scheduling latency >= 0, so the host/device relation is the lower envelope of the pairs.
Over a sliding window, host - device = offset + drift * (device - ref): the drift is the
least-squares slope through the minimum of each of ~10 time slices (the least delayed
frames), estimated once the window spans `min_span_s`; the line is then lowered to the
smallest residual, so mapped stamps carry the minimal latency seen, not each arrival's
jitter. Drift (ppm) is the clock-rate difference.
"""

from __future__ import annotations

import collections
import threading

import numpy as np


class ClockMapper:
    def __init__(self, window: int = 2000, min_span_s: float = 10.0, slices: int = 10) -> None:
        self._pairs: collections.deque = collections.deque(maxlen=window)
        self.min_span_ns = min_span_s * 1e9
        self.slices = slices
        self._ref_dev = 0
        self._y0 = 0  # ns, host - device of the oldest pair (integer reference)
        self._offset = 0.0  # ns, host - device - _y0 at device == _ref_dev
        self._drift = 0.0  # ns per ns
        self.resets = 0

    def reset(self) -> None:
        """Forget the history (a camera reconnected: its clock may have restarted)."""
        self._pairs.clear()
        self.resets += 1

    def update(self, device_ns: int, host_ns: int) -> int:
        """Add one (device, host) pair and return the device stamp mapped to host time."""
        if self._pairs and device_ns <= self._pairs[-1][0]:
            self.reset()  # the device clock went backwards: camera restarted
        self._pairs.append((int(device_ns), int(host_ns)))
        d = np.array([p[0] for p in self._pairs], dtype=np.int64)
        h = np.array([p[1] for p in self._pairs], dtype=np.int64)
        # integer differences first: host stamps (~1e18 ns) would lose ~256 ns in float64
        self._ref_dev = int(d[0])
        self._y0 = int(h[0] - d[0])
        x = (d - d[0]).astype(np.float64)
        y = ((h - d) - self._y0).astype(np.float64)
        if x[-1] >= self.min_span_ns and len(x) >= 2 * self.slices:
            edges = np.linspace(0, len(x), self.slices + 1).astype(int)
            idx = np.array([lo + int(np.argmin(y[lo:hi])) for lo, hi in zip(edges[:-1], edges[1:])])
            a, b = np.polyfit(x[idx], y[idx], 1)
        else:
            b, a = float(np.min(y)), 0.0
        self._offset = b + float(np.min(y - (b + a * x)))
        self._drift = float(a)
        return self.map(device_ns)

    def map(self, device_ns: int) -> int:
        return int(device_ns) + self._y0 + int(round(self._offset + self._drift * (device_ns - self._ref_dev)))

    @property
    def offset_ns(self) -> float:
        """Current host - device offset (ns) at the newest pair."""
        if not self._pairs:
            return 0.0
        return self._y0 + self._offset + self._drift * (self._pairs[-1][0] - self._ref_dev)

    @property
    def drift_ppm(self) -> float:
        return self._drift * 1e6

    @property
    def pairs(self) -> int:
        return len(self._pairs)


class LoopedStamps:
    """Recorded stamps of one camera made increasing across loops of a recording: when the
    recording starts over, stamps go on one frame period after the last one."""

    def __init__(self) -> None:
        self._shift = 0
        self._prev: int | None = None
        self._period: int | None = None

    def __call__(self, stamp_ns: int) -> int:
        t = stamp_ns + self._shift
        if self._prev is not None and t <= self._prev:  # the recording started over
            step = self._period or 1
            self._shift += self._prev + step - t
            t = self._prev + step
        elif self._prev is not None:
            self._period = t - self._prev
        self._prev = t
        return t


class PlaybackClock:
    """When recorded frames are due and how they are stamped, shared by the threads of all
    cameras (thread-safe): the first frame fixes the epoch (monotonic and wall time, and its
    recorded stamp), so frames of one recorded instant are due, and with `restamp` stamped, at
    one instant on every camera. rate: x real time (0 = as fast as read, no pacing)."""

    def __init__(self, rate: float, restamp: bool) -> None:
        self.rate = float(rate)
        self.restamp = bool(restamp)
        self._lock = threading.Lock()
        self._epoch: tuple[float, int, int] | None = None

    def schedule(self, t_ns: int, now_mono: float, now_wall_ns: int) -> tuple[int, float | None]:
        """(stamp to publish, monotonic time the frame is due or None when not paced) of a
        frame with recorded stamp t_ns (after LoopedStamps)."""
        with self._lock:
            if self._epoch is None:
                self._epoch = (now_mono, now_wall_ns, t_ns)
            mono0, wall0, t0 = self._epoch
        if self.rate <= 0:
            return t_ns, None
        stamp = wall0 + int((t_ns - t0) / self.rate) if self.restamp else t_ns
        return stamp, mono0 + (t_ns - t0) / 1e9 / self.rate

    def superseded(self, due: float, period: float, now_mono: float) -> bool:
        """Replayed as a live camera (`restamp`): is a frame due at `due` (monotonic s) already
        more than two frame periods late? A live camera's newer frames would have replaced it;
        sending it lets a graph slower than the camera (the CNN) fall behind without bound."""
        return self.restamp and period > 0 and now_mono - due > 2.0 * period
