"""Mapping a camera's own clock to ROS (host) time: estimated offset, tracked drift.

Each frame gives a pair (device stamp, host arrival time). Arrival = exposure + transfer and
scheduling latency >= 0, so the host/device relation is the lower envelope of the pairs.
Over a sliding window we fit host - device = offset + drift * device by least squares, then
lower the line to the smallest residual: the mapped stamps carry the minimal latency seen,
not the jitter of each arrival. Drift (ppm) is the clock-rate difference.
"""

from __future__ import annotations

import collections

import numpy as np


class ClockMapper:
    def __init__(self, window: int = 200, min_pairs_for_drift: int = 20) -> None:
        self._pairs: collections.deque = collections.deque(maxlen=window)
        self.min_pairs_for_drift = min_pairs_for_drift
        self._ref_dev = 0
        self._offset = 0.0  # ns, host - device at device == _ref_dev
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
        d = np.array([p[0] for p in self._pairs], dtype=np.float64)
        h = np.array([p[1] for p in self._pairs], dtype=np.float64)
        self._ref_dev = int(d[0])
        x = d - self._ref_dev
        y = h - d
        if len(d) >= self.min_pairs_for_drift and x[-1] > 0:
            A = np.stack([np.ones_like(x), x], axis=1)
            (b, a), *_ = np.linalg.lstsq(A, y, rcond=None)
        else:
            b, a = float(np.median(y)), 0.0
        self._offset = b + float(np.min(y - (b + a * x)))
        self._drift = float(a)
        return self.map(device_ns)

    def map(self, device_ns: int) -> int:
        return int(round(device_ns + self._offset + self._drift * (device_ns - self._ref_dev)))

    @property
    def offset_ns(self) -> float:
        """Current host - device offset (ns) at the newest pair."""
        if not self._pairs:
            return 0.0
        return self._offset + self._drift * (self._pairs[-1][0] - self._ref_dev)

    @property
    def drift_ppm(self) -> float:
        return self._drift * 1e6

    @property
    def pairs(self) -> int:
        return len(self._pairs)
