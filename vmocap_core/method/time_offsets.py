"""Camera time offsets from the CNN's 2D keypoints.

The method assumes synchronized cameras (paper II-A). Cameras without a common trigger (V4L2
webcams) or videos cut apart by hand can be frames out of step, which looks like a calibration
error: a moving person's keypoints in that camera miss the other cameras' rays. Here each
camera's 2D keypoint series is shifted against the others' by whole frame sets and compared with
the projection of the other cameras' triangulation; the shift at which its error is smallest is
its offset (refined between frame sets by a parabola through the three errors around it).

A camera turned or moved since calibration is off by a near-constant amount, and while the
subject moves one way a time shift explains part of such an offset too: so each camera's
constant 2D offset is removed before its error is measured, and only the part of the error that
follows the image motion is left for a shift to explain.
"""

from __future__ import annotations

from concurrent.futures import Future, ThreadPoolExecutor
from dataclasses import dataclass

import numpy as np

from ..cameras.projection import Rig
from ..keypoints import KEYPOINTS
from ..pcm.peaks import camera_keypoints
from ..pcm.views import PcmViews
from .triangulation import triangulate

MAX_SHIFT = 4  # frame sets each way
MIN_WEIGHT = 0.5  # keypoints the CNN is confident of (the demo report's rule)
# A verdict needs the best shift at least a frame set away and a clearly smaller error there.
MIN_GAIN = 0.075
PROBE_FRAMES = 120  # frame sets a live probe collects (2 s at 60 Hz)
PROBE_EVERY_S = 60.0  # at most one live probe (~0.05 s of CPU, in a thread) this often


@dataclass
class TimeOffset:
    camera: str
    frames: float  # > 0: this camera's images lag: the one stamped t shows the scene at t - frames
    error_px: float  # median error of its keypoints as recorded, against the others' triangulation, constant offset removed
    best_error_px: float  # the same with its series shifted by round(frames)

    @property
    def out_of_step(self) -> bool:
        return bool(abs(self.frames) >= 1.0 and self.best_error_px < (1.0 - MIN_GAIN) * self.error_px)

    def describe(self, fps: float) -> str:
        return (f"{self.camera}: images lag the others by {self.frames:+.1f} frame sets ({1e3 * self.frames / fps:+.0f} ms); "
                f"reprojection {self.error_px:.1f} px as stamped, {self.best_error_px:.1f} px shifted back")


def camera_time_offsets(rig: Rig, uv: np.ndarray, weights: np.ndarray, max_shift: int = MAX_SHIFT,
                        min_weight: float = MIN_WEIGHT) -> list[TimeOffset]:
    """uv (N, C, 25, 2) pixels and weights (N, C, 25) of N consecutive frame sets (e.g.
    `peaks.camera_keypoints` per frame set; weight 0 = not seen). One TimeOffset per camera;
    NaN figures for a camera without enough confident keypoints.

    A late camera also pulls the triangulated points, so the others seem a little out of step
    too: the camera found most clearly out of step is shifted back first and the rest
    estimated again, until none is left."""
    uv = np.asarray(uv, dtype=np.float64)
    w = np.where(np.isfinite(uv).all(axis=-1), np.nan_to_num(np.asarray(weights, dtype=np.float64)), 0.0)
    found: dict[int, TimeOffset] = {}
    while True:
        est = {c: _estimate(rig, uv, w, c, max_shift, min_weight) for c in range(uv.shape[1]) if c not in found}
        late = {c: o for c, o in est.items() if o.out_of_step}
        if not late:
            break
        c = max(late, key=lambda k: 1.0 - late[k].best_error_px / late[k].error_px)
        found[c] = late[c]
        uv, w = _shifted(uv, w, c, int(round(late[c].frames)))
    return [found.get(c) or est[c] for c in range(uv.shape[1])]


def _shifted(uv: np.ndarray, w: np.ndarray, c: int, s: int) -> tuple[np.ndarray, np.ndarray]:
    """Camera c's series read s frame sets later (its frame t + s at t); the ends it lacks unseen."""
    n = len(uv)
    a, b = max(0, -s), min(n, n - s)
    u, ww = uv.copy(), w.copy()
    u[:, c], ww[:, c] = np.nan, 0.0
    u[a:b, c], ww[a:b, c] = uv[a + s:b + s, c], w[a + s:b + s, c]
    return u, ww


def _estimate(rig: Rig, uv: np.ndarray, w: np.ndarray, c: int, max_shift: int, min_weight: float) -> TimeOffset:
    """Camera c's reprojection error with its series shifted by -max_shift..max_shift, against
    the other cameras' triangulation (camera c left out, so it cannot pull the points towards
    itself) and after removing camera c's constant 2D offset: a camera turned or moved since
    calibration shifts all its keypoints by about the same amount, which, while the subject
    moves one way, a time shift would otherwise partly explain. What is left for a shift to
    explain is the part of the error that follows the image motion."""
    n, n_cams = uv.shape[:2]
    others = np.ones(n_cams, bool)
    others[c] = False
    w_others = w.copy()
    w_others[:, c] = 0.0
    X, _ = triangulate(rig, uv.transpose(1, 0, 2, 3).reshape(n_cams, -1, 2), w_others.transpose(1, 0, 2).reshape(n_cams, -1))
    proj = rig[c].project(np.nan_to_num(X))[0].reshape(n, -1, 2)
    seen = np.isfinite(X).all(axis=1).reshape(n, -1) & ((w[:, others] > 0).sum(axis=1) >= 2)
    shifts = np.arange(-max_shift, max_shift + 1)
    err = np.full(len(shifts), np.nan)
    for k, s in enumerate(shifts):
        u, ww = _shifted(uv, w, c, int(s))
        r = (u[:, c] - proj)[seen & (ww[:, c] >= min_weight) & np.isfinite(u[:, c]).all(axis=-1)]
        if len(r) >= 25:
            err[k] = float(np.median(np.linalg.norm(r - np.median(r, axis=0), axis=1)))
    return _offset(rig.names[c], shifts, err)


def _offset(name: str, shifts: np.ndarray, err: np.ndarray) -> TimeOffset:
    zero = float(err[shifts == 0][0])
    if not np.isfinite(err).any() or not np.isfinite(zero):
        return TimeOffset(name, float("nan"), zero, float("nan"))
    k = int(np.nanargmin(err))
    frames = float(shifts[k])
    if 0 < k < len(err) - 1 and np.isfinite(err[k - 1 : k + 2]).all():
        lo, mid, hi = err[k - 1], err[k], err[k + 1]
        curv = lo - 2 * mid + hi
        if curv > 0:  # vertex of the parabola through the three errors
            frames += 0.5 * (lo - hi) / curv
    return TimeOffset(name, float(frames), zero, float(err[k]))


class OffsetProbe:
    """Collects the cameras' 2D keypoints of `frames` consecutive frame-set periods on request (a
    live node asks when a camera disagrees with the others), for `camera_time_offsets` to tell a
    camera out of step from a moved one. Frame sets that did not come (dropped) are left unseen;
    a jump of more than MAX_GAP periods, or back, starts the collection again."""

    MAX_GAP = 10

    def __init__(self, n_cameras: int, fps: float, frames: int = PROBE_FRAMES) -> None:
        self.n_cameras = n_cameras
        self.period_ns = 1e9 / fps
        self.frames = frames
        self.collecting = False
        self._uv: list[np.ndarray] = []
        self._w: list[np.ndarray] = []
        self._last: int | None = None

    def start(self) -> None:
        self.collecting, self._uv, self._w, self._last = True, [], [], None

    def add(self, pcm: PcmViews) -> tuple[np.ndarray, np.ndarray] | None:
        """One frame set while collecting; (uv (N, C, 25, 2), weights (N, C, 25)) once full."""
        if not self.collecting:
            return None
        if self._last is not None:
            steps = int(round((pcm.stamp_ns - self._last) / self.period_ns))
            if steps <= 0 or steps > self.MAX_GAP:
                self._uv, self._w = [], []
            else:
                for _ in range(steps - 1):  # the frame sets that did not come
                    self._uv.append(np.full((self.n_cameras, len(KEYPOINTS), 2), np.nan))
                    self._w.append(np.zeros((self.n_cameras, len(KEYPOINTS))))
        self._last = pcm.stamp_ns
        uv, w = camera_keypoints(pcm, self.n_cameras)
        self._uv.append(uv)
        self._w.append(w)
        if len(self._uv) < self.frames:
            return None
        self.collecting = False
        return np.array(self._uv[-self.frames:]), np.array(self._w[-self.frames:])


class TimingCheck:
    """What a live node runs while it tracks: at most every `every_s`, an OffsetProbe, estimated
    in a worker thread (numpy's linear algebra releases the GIL) so the caller does not wait;
    `warning()` is the WARN for the cameras the last probe found out of step, `note(camera)` says
    what it found for one camera (for a diagnostic that names it)."""

    def __init__(self, rig: Rig, fps: float, every_s: float = PROBE_EVERY_S, frames: int = PROBE_FRAMES) -> None:
        self.rig, self.fps, self.every_s = rig, fps, every_s
        self.probe = OffsetProbe(len(rig), fps, frames)
        self.found: dict[str, TimeOffset] = {}
        self._job: Future | None = None
        self._pool: ThreadPoolExecutor | None = None
        self._due = 0.0
        self._failed = ""

    def request(self, now: float) -> None:
        """Probe (`now`: monotonic seconds) unless one runs or ran within `every_s`."""
        if self._job is None and not self.probe.collecting and now >= self._due:
            self.probe.start()
            self._due = now + self.every_s

    def add(self, pcm: PcmViews) -> None:
        """A tracked frame set (nothing to do unless a probe collects)."""
        full = self.probe.add(pcm)
        if full is not None:
            self._pool = self._pool or ThreadPoolExecutor(1, thread_name_prefix="vmocap-timing")
            self._job = self._pool.submit(camera_time_offsets, self.rig, *full)

    def _collect(self) -> None:
        """Take a finished probe's result."""
        if self._job is not None and self._job.done():
            job, self._job = self._job, None
            try:
                self.found, self._failed = {o.camera: o for o in job.result()}, ""
            except Exception as exc:  # noqa: BLE001 - a diagnostic of a diagnostic: say so, go on
                self._failed = f"the probe failed ({exc})"

    def late(self) -> list[TimeOffset]:
        """The cameras the last probe found out of step (none before the first)."""
        self._collect()
        return [o for o in self.found.values() if o.out_of_step]

    @property
    def failed(self) -> str:
        """Why the last probe failed ("" when it did not)."""
        self._collect()
        return self._failed

    def warning(self) -> str:
        """A live node's WARN: the cameras the last probe found out of step, or why it failed
        ("" when neither)."""
        late = self.late()
        if late:
            return ("camera out of step: " + "; ".join(o.describe(self.fps) for o in late)
                    + " (cameras without a common trigger, or videos cut apart?)")
        return f"camera time offsets: {self._failed}" if self._failed else ""

    def note(self, camera: str) -> str:
        """" Timing: ..." for a diagnostic about `camera` ("" before the probe said anything)."""
        self._collect()
        o = self.found.get(camera)
        if o is None or not np.isfinite(o.frames):
            return f" Timing: {self._failed}" if self._failed else ""
        if o.out_of_step:
            return f" Timing: {o.describe(self.fps)}: out of step"
        return f" Timing: in step ({o.frames:+.1f} frame sets)"

    def close(self) -> None:
        if self._pool is not None:
            self._pool.shutdown(wait=True, cancel_futures=True)
