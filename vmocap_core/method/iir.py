"""Causal IIR low-pass filtering of trajectories, one sample at a time (paper II-F)."""

from __future__ import annotations

import numpy as np
from scipy import signal


class LowPassFilter:
    """Butterworth low-pass of configurable order and cutoff, as second-order sections,
    applied causally to a vector of channels per call.

    The state starts in steady state at the first sample, so a constant input passes without a
    start-up transient (a tracker that starts on a standing person does not see it fly in).
    """

    def __init__(self, order: int, cutoff_hz: float, rate_hz: float, lag_compensation: bool = False) -> None:
        if order < 1:
            raise ValueError("filter order must be >= 1")
        if not 0 < cutoff_hz < rate_hz / 2:
            raise ValueError(f"cutoff {cutoff_hz} Hz must lie in (0, {rate_hz / 2}) Hz for a {rate_hz} Hz signal")
        self.order = order
        self.cutoff_hz = cutoff_hz
        self.rate_hz = rate_hz
        self.sos = signal.butter(order, cutoff_hz, btype="low", fs=rate_hz, output="sos")
        self._zi_unit = signal.sosfilt_zi(self.sos)  # (S, 2) steady state for a unit input
        self._z: np.ndarray | None = None  # (S, 2, N)
        # Optional lead term y + g (y - y_prev), g = the DC group delay in samples: still a
        # causal IIR filter, H'(z) = H(z) (1 + g (1 - z^-1)), but with zero lag on ramps, so a
        # subject moving at constant speed is not trailed by the filter's delay.
        self.lead = self.group_delay_s(0.0) * rate_hz if lag_compensation else 0.0
        self._y_prev: np.ndarray | None = None

    def reset(self) -> None:
        self._z = None
        self._y_prev = None

    def __call__(self, x: np.ndarray) -> np.ndarray:
        """Filter one sample of any shape; returns the filtered sample of the same shape."""
        x = np.asarray(x, dtype=np.float64)
        shape = x.shape
        v = x.reshape(-1)
        if self._z is None or self._z.shape[2] != v.size:
            self._z = self._zi_unit[:, :, None] * v[None, None, :]
        z = self._z
        # Direct form II transposed, section by section.
        for s, (b0, b1, b2, _, a1, a2) in enumerate(self.sos):
            y = b0 * v + z[s, 0]
            z[s, 0] = b1 * v - a1 * y + z[s, 1]
            z[s, 1] = b2 * v - a2 * y
            v = y
        if self.lead:
            prev = v if self._y_prev is None else self._y_prev
            self._y_prev = v.copy()
            v = v + self.lead * (v - prev)
        return v.reshape(shape)

    def frequency_response(self, freqs_hz: np.ndarray) -> np.ndarray:
        """|H(f)| at the given frequencies."""
        f = np.asarray(freqs_hz, float)
        _, h = signal.sosfreqz(self.sos, worN=f, fs=self.rate_hz)
        if self.lead:
            h = h * (1 + self.lead * (1 - np.exp(-2j * np.pi * f / self.rate_hz)))
        return np.abs(h)

    def group_delay_s(self, freq_hz: float = 0.0) -> float:
        """Group delay at a frequency (seconds): the lag the causal filter adds."""
        b, a = signal.sos2tf(self.sos)
        _, gd = signal.group_delay((b, a), w=[max(freq_hz, 1e-3)], fs=self.rate_hz)
        return float(gd[0]) / self.rate_hz
