"""Non-causal smoothing of keypoint trajectories: the Rauch-Tung-Striebel (RTS) smoother on a
kinematic motion model, over a whole segment (offline) or over a sliding window of a few frames
(fixed-lag, live), and a zero-phase Gaussian smoother for comparison.

Motion model, per coordinate: a constant-velocity ("cv", white acceleration) or constant-
acceleration ("ca", white jerk) state, observed in position. Every channel shares the model
and the noise levels, so the covariances are the same for all channels: they are propagated
once (n x n) and the states of all channels (n, C) are updated together.
"""

from __future__ import annotations

from collections import deque
from dataclasses import dataclass
from typing import Iterator

import numpy as np
from scipy.ndimage import gaussian_filter1d


@dataclass(frozen=True)
class MotionModel:
    """Discrete kinematic model at `rate_hz`: process noise spectral density `process_noise`
    ((m/s^2)^2/Hz for cv, (m/s^3)^2/Hz for ca), measurement noise std `measurement_noise_m`."""

    kind: str  # "cv" | "ca"
    process_noise: float
    measurement_noise_m: float
    rate_hz: float

    def __post_init__(self) -> None:
        if self.kind not in ("cv", "ca"):
            raise ValueError(f"motion model must be 'cv' or 'ca', not {self.kind!r}")
        if self.process_noise <= 0 or self.measurement_noise_m <= 0 or self.rate_hz <= 0:
            raise ValueError("process noise, measurement noise and rate must be positive")

    def matrices(self) -> tuple[np.ndarray, np.ndarray, float]:
        """(F, Q, R) of the discretized model (continuous white-noise integration)."""
        dt = 1.0 / self.rate_hz
        q = self.process_noise
        if self.kind == "cv":
            F = np.array([[1.0, dt], [0.0, 1.0]])
            Q = q * np.array([[dt**3 / 3, dt**2 / 2], [dt**2 / 2, dt]])
        else:
            F = np.array([[1.0, dt, dt * dt / 2], [0.0, 1.0, dt], [0.0, 0.0, 1.0]])
            Q = q * np.array([[dt**5 / 20, dt**4 / 8, dt**3 / 6],
                              [dt**4 / 8, dt**3 / 3, dt**2 / 2],
                              [dt**3 / 6, dt**2 / 2, dt]])
        return F, Q, self.measurement_noise_m**2


class _Kalman:
    """Forward Kalman filter shared by the smoothers; keeps what the RTS pass needs."""

    def __init__(self, model: MotionModel) -> None:
        self.F, self.Q, self.R = model.matrices()
        self.n = self.F.shape[0]
        self.x: np.ndarray | None = None  # (n, C)
        self.P: np.ndarray | None = None

    def reset(self) -> None:
        self.x = self.P = None

    def step(self, z: np.ndarray) -> tuple[np.ndarray, np.ndarray, np.ndarray, np.ndarray]:
        """Filter one measurement (C,) (NaN: none this frame). Returns (x_pred, P_pred,
        x_filt, P_filt)."""
        if self.x is None:
            # Start at the first measurement, at rest, with the measurement's uncertainty in
            # position and a broad one in the derivatives.
            self.x = np.zeros((self.n, z.size))
            self.x[0] = z
            self.P = np.diag([self.R] + [1e6] * (self.n - 1))
            return self.x.copy(), self.P.copy(), self.x.copy(), self.P.copy()
        xp = self.F @ self.x
        Pp = self.F @ self.P @ self.F.T + self.Q
        if np.isfinite(z).all():
            K = Pp[:, 0] / (Pp[0, 0] + self.R)  # (n,): H = [1, 0, ...]
            self.x = xp + K[:, None] * (z - xp[0])[None, :]
            self.P = Pp - np.outer(K, Pp[0])
        else:
            self.x, self.P = xp, Pp
        return xp, Pp, self.x.copy(), self.P.copy()


def _rts_back(F: np.ndarray, xp: list[np.ndarray], Pp: list[np.ndarray], xf: list[np.ndarray],
              Pf: list[np.ndarray]) -> Iterator[np.ndarray]:
    """RTS backward recursion over filtered frames: yields the smoothed states (n, C) from the
    last frame to the first; xp/Pp[k] are the predictions of frame k."""
    xs, Ps = xf[-1], Pf[-1]
    yield xs
    for k in range(len(xf) - 2, -1, -1):
        G = Pf[k] @ F.T @ np.linalg.inv(Pp[k + 1])
        xs = xf[k] + G @ (xs - xp[k + 1])
        Ps = Pf[k] + G @ (Ps - Pp[k + 1]) @ G.T
        yield xs


def rts_smooth(x: np.ndarray, model: MotionModel) -> np.ndarray:
    """Fixed-interval smoothing of a trajectory (T, ...) (NaN samples: no measurement that
    frame, all channels of a frame together). Returns the smoothed positions (T, ...)."""
    x = np.asarray(x, dtype=np.float64)
    T = x.shape[0]
    flat = x.reshape(T, -1)
    kf = _Kalman(model)
    steps = [kf.step(flat[t]) for t in range(T)]
    back = _rts_back(kf.F, *(list(v) for v in zip(*steps)))
    out = np.array([xs[0] for xs in back])[::-1]
    return out.reshape(x.shape)


class FixedLagSmoother:
    """Live smoothing with a delay of `lag` frames: each call filters one sample (...) and
    returns the RTS estimate of the sample `lag` frames back given everything up to now, or
    None while the first `lag` samples fill the window."""

    def __init__(self, model: MotionModel, lag: int) -> None:
        if lag < 1:
            raise ValueError("lag must be >= 1 frame")
        self.lag = int(lag)
        self._kf = _Kalman(model)
        self._hist: deque[tuple[np.ndarray, ...]] = deque(maxlen=self.lag + 1)

    def reset(self) -> None:
        self._kf.reset()
        self._hist.clear()

    def __call__(self, x: np.ndarray) -> np.ndarray | None:
        x = np.asarray(x, dtype=np.float64)
        self._hist.append(self._kf.step(x.reshape(-1)))
        if len(self._hist) <= self.lag:
            return None
        *_, oldest = _rts_back(self._kf.F, *(list(v) for v in zip(*self._hist)))  # down to the window's oldest frame
        return oldest[0].reshape(x.shape)


def gaussian_smooth(x: np.ndarray, sigma_frames: float) -> np.ndarray:
    """Zero-phase Gaussian smoothing along time (edges: the nearest sample repeated)."""
    return gaussian_filter1d(np.asarray(x, dtype=np.float64), sigma_frames, axis=0, mode="nearest")


def runs(mask: np.ndarray) -> list[slice]:
    """Maximal runs of True in a boolean sequence, as slices (the segments a smoother may
    cross: never a gap)."""
    m = np.concatenate([[False], np.asarray(mask, bool), [False]])
    d = np.flatnonzero(np.diff(m.astype(np.int8)))
    return [slice(int(a), int(b)) for a, b in zip(d[::2], d[1::2])]
