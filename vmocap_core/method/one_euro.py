"""Speed-adaptive causal low-pass of keypoint trajectories (the "1-euro" filter of Casiez,
Roussel and Vogel, CHI 2012), our alternative to the paper's fixed IIR filter (II-F).

A first-order low-pass whose cutoff rises with each keypoint's speed: fc = min_cutoff +
beta * |v| (v itself low-passed at derivative_cutoff). A still or slow keypoint is smoothed
hard (jitter is what shows there); a fast one is hardly delayed (lag is what shows there).
One fixed cutoff has to trade these off for every keypoint at once.
"""

from __future__ import annotations

import numpy as np


class OneEuroFilter:
    """Filters one sample (..., 3) of keypoint positions per call; the speed is the norm over
    the last axis, so each keypoint adapts on its own. NaN samples pass through and restart
    that keypoint's state."""

    def __init__(self, min_cutoff_hz: float, beta: float, rate_hz: float, derivative_cutoff_hz: float = 2.0) -> None:
        """beta: Hz of cutoff per m/s of speed."""
        if not 0 < min_cutoff_hz < rate_hz / 2 or not 0 < derivative_cutoff_hz < rate_hz / 2:
            raise ValueError(f"cutoffs must lie in (0, {rate_hz / 2}) Hz for a {rate_hz} Hz signal")
        if beta < 0:
            raise ValueError("beta must be >= 0")
        self.min_cutoff_hz = float(min_cutoff_hz)
        self.beta = float(beta)
        self.rate_hz = float(rate_hz)
        self.derivative_cutoff_hz = float(derivative_cutoff_hz)
        self._x: np.ndarray | None = None
        self._v: np.ndarray | None = None

    def reset(self) -> None:
        self._x = self._v = None

    @staticmethod
    def _alpha(cutoff_hz: np.ndarray | float, rate_hz: float) -> np.ndarray | float:
        """Smoothing factor of a first-order low-pass at this cutoff (exact for the sampling)."""
        tau = 1.0 / (2.0 * np.pi * np.asarray(cutoff_hz))
        return 1.0 / (1.0 + tau * rate_hz)

    def __call__(self, x: np.ndarray, dt: float | None = None) -> np.ndarray:
        """dt: seconds since the previous sample when frames were skipped (None: 1 / rate_hz);
        the smoothing factors follow the real interval, so a skipped frame set is no jump."""
        x = np.asarray(x, dtype=np.float64)
        if self._x is None or self._v is None or self._x.shape != x.shape:
            self._x, self._v = x.copy(), np.zeros_like(x)
            return x.copy()
        rate = self.rate_hz if dt is None or not dt > 0 else 1.0 / dt
        fresh = ~np.isfinite(self._x).all(axis=-1, keepdims=True)  # keypoints without a state
        v = np.where(fresh, 0.0, (x - self._x) * rate)
        a_v = self._alpha(self.derivative_cutoff_hz, rate)
        self._v = np.where(fresh, 0.0, a_v * v + (1.0 - a_v) * self._v)
        speed = np.linalg.norm(self._v, axis=-1, keepdims=True)
        a = self._alpha(self.min_cutoff_hz + self.beta * speed, rate)
        self._x = np.where(fresh, x, a * x + (1.0 - a) * self._x)
        return self._x.copy()
