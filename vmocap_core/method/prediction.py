"""Where the body will be at the next frame set: the crops of the CNN follow a turning body.

The paper crops and rotates each camera's input by the skeleton of the previous frame (III-B).
A body that turns over in under a second (a backflip, a roll, getting up) turns by 10-20 degrees
between two frame sets at 30-60 Hz, more when an overloaded graph skips frame sets, and the
CNN then sees a body tilted against its crop. `BodyPredictor` extrapolates the last fed-back
skeleton to the new frame set's stamp by the body's rigid motion between the last two
feedbacks (its angular and linear velocity), so the crops' rotation and centre lead rather than
lag. The limbs' own motion is not extrapolated: the crop's margin covers it, and extrapolating
noisy limbs would make the crop jitter.
"""

from __future__ import annotations

import numpy as np

from ..calibration.geometry import rigid_align, rodrigues
from .results import seed_of, skeleton_of

# Extrapolate at most this many feedback intervals ahead, from feedbacks at most MAX_GAP_S apart:
# beyond that the velocity is stale and the last skeleton is the better guess.
MAX_AHEAD = 3.0
MAX_GAP_S = 0.2
MAX_TURN_RAD = np.radians(60.0)  # a larger predicted turn is a tracking glitch, not a motion


def rigid_motion(a: np.ndarray, b: np.ndarray) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """Least-squares rotation R and centroids ca, cb with b ~ R (a - ca) + cb (Kabsch), over the
    rows finite in both (N, 3) point sets."""
    ok = np.isfinite(a).all(axis=1) & np.isfinite(b).all(axis=1)
    pa, pb = a[ok], b[ok]
    R, _ = rigid_align(pa, pb)
    return R, pa.mean(axis=0), pb.mean(axis=0)


def rotation_power(R: np.ndarray, s: float, max_angle: float = MAX_TURN_RAD) -> np.ndarray:
    """R^s (the same axis, s times the angle, clipped to max_angle), by Rodrigues' formula."""
    angle = float(np.arccos(np.clip((np.trace(R) - 1.0) / 2.0, -1.0, 1.0)))
    if angle < 1e-9:
        return np.eye(3)
    axis = np.array([R[2, 1] - R[1, 2], R[0, 2] - R[2, 0], R[1, 0] - R[0, 1]])
    n = np.linalg.norm(axis)
    if n < 1e-12:  # a half turn between two feedbacks: no velocity to trust
        return np.eye(3)
    theta = float(np.clip(s * angle, -max_angle, max_angle))
    return rodrigues(axis * (theta / n))[0]


class BodyPredictor:
    """Feed it every fed-back skeleton (`update`, None or NaN when not tracking), ask it for the
    skeleton at a frame set's stamp (`predict`). Deterministic: the same feedbacks give the same
    prediction in the node graph and offline."""

    def __init__(self, enabled: bool = True) -> None:
        self.enabled = enabled
        self._last: tuple[int, np.ndarray] | None = None
        self._before: tuple[int, np.ndarray] | None = None
        self._seed: np.ndarray | None = None  # the last feedback when it was a seed (results.seed_of)

    @classmethod
    def for_provider(cls, provider: object) -> "BodyPredictor":
        """The predictor the crops of a PCM provider follow: its `crop_prediction` ("rigid"), or
        the previous skeleton as it was for providers without crops (heatmap bags, synthetic)."""
        return cls(enabled=getattr(provider, "crop_prediction", "previous") == "rigid")

    def update(self, stamp_ns: int, keypoints: np.ndarray | None) -> None:
        self._seed = keypoints if seed_of(keypoints) is not None else None
        if skeleton_of(keypoints) is None:
            self._last = self._before = None
            return
        kp = np.array(keypoints, dtype=np.float64)
        if self._last is not None and stamp_ns <= self._last[0]:
            if stamp_ns == self._last[0]:  # the same feedback again (a latched topic)
                self._last = (stamp_ns, kp)
            return
        self._before, self._last = self._last, (int(stamp_ns), kp)

    def predict(self, stamp_ns: int) -> np.ndarray | None:
        """The skeleton expected at stamp_ns; the last one as it was when there is no velocity;
        a seed fed back is passed on as it is (where the detector looks for the subject)."""
        if self._last is None:
            return self._seed
        t1, kp1 = self._last
        if not self.enabled or self._before is None:
            return kp1
        t0, kp0 = self._before
        gap = (t1 - t0) * 1e-9
        if gap <= 0 or gap > MAX_GAP_S or stamp_ns <= t1:
            return kp1
        s = min((stamp_ns - t1) * 1e-9 / gap, MAX_AHEAD)
        R, c0, c1 = rigid_motion(kp0, kp1)
        velocity = c1 - c0
        return (kp1 - c1) @ rotation_power(R, s).T + c1 + s * velocity
