"""Which camera disagrees with the others: per-camera reprojection residuals of the virtual markers.

A camera that was moved or turned after calibration still sees the person, so tracking goes on
with the views that agree (the lattice search and the robust triangulation outvote one view),
and nothing in the output tells the user. Its PCM peaks, though, stay far from where the
markers project in that camera while the others' stay close: the median distance per camera,
over the keypoints its maps are confident about, names it.
"""

from __future__ import annotations

from collections import deque

import numpy as np

from ..cameras.projection import Rig
from ..pcm.peaks import camera_keypoints
from ..pcm.views import PcmViews

MIN_PEAK = 0.5  # confident keypoints only (the CNN's maps peak at ~0.5 on anything)
MIN_KEYPOINTS = 4  # fewer confident keypoints in a view: no figure for it this time
ODD_MIN_PX = 15.0  # a camera is odd when its residual exceeds this ...
ODD_RATIO = 3.0  # ... and this many times the median of the other cameras


def camera_residuals(rig: Rig, pcm: PcmViews, markers: np.ndarray) -> dict[str, float]:
    """Per camera, the median pixel distance between the projected markers (25, 3) and that
    camera's PCM centroids, over the keypoints the camera is confident about (views of one
    camera: the better one per keypoint). Cameras without enough confident keypoints are left out."""
    uv, peak = pcm.centroids()  # (V, J, 2) image px, (V, J)
    cam = np.asarray(pcm.camera, dtype=np.intp)
    kp = np.asarray(pcm.keypoints, dtype=np.intp)
    proj, front = rig.project(np.asarray(markers, dtype=np.float64)[kp])  # (C, J, 2), (C, J)
    err = np.linalg.norm(uv - proj[cam], axis=-1)  # (V, J)
    ok = (peak >= MIN_PEAK) & front[cam] & np.isfinite(err) & np.asarray(pcm.valid, bool)
    err = np.where(ok, err, np.inf)
    out: dict[str, float] = {}
    for c in np.unique(cam):
        best = err[cam == c].min(axis=0)  # per keypoint, the camera's better view
        best = best[np.isfinite(best)]
        if best.size >= MIN_KEYPOINTS:
            out[rig[int(c)].name] = float(np.median(best))
    return out


class OddCamera:
    """Rolling per-camera residuals and the camera that disagrees with the others, if any."""

    def __init__(self, window: int = 15) -> None:
        self.history: dict[str, deque[float]] = {}
        self.window = window

    def add(self, residuals: dict[str, float]) -> None:
        for name, r in residuals.items():
            self.history.setdefault(name, deque(maxlen=self.window)).append(r)

    def medians(self) -> dict[str, float]:
        return {n: float(np.median(h)) for n, h in self.history.items() if h}

    def odd(self) -> tuple[str, float, float] | None:
        """(camera, its median residual px, the others' median) when one camera is far off."""
        med = self.medians()
        if len(med) < 3:  # two cameras cannot outvote each other
            return None
        name = max(med, key=med.__getitem__)
        others = float(np.median([v for n, v in med.items() if n != name]))
        if med[name] >= ODD_MIN_PX and med[name] >= ODD_RATIO * max(others, 1.0):
            return name, med[name], others
        return None


# A camera moved along a few centimetres is mostly absorbed by the markers (the residuals above
# stay at the views' noise), but its epipolar geometry with each other camera is off by a
# constant: per camera pair, the mean *signed* distance of one camera's 2D keypoints from the
# epipolar lines of the other's averages the noise away and keeps that offset.
# Thresholds: with the real CNN on rendered clips (exact calibration, 1024x768) one camera's
# pairs reached 3.3 mrad (a person getting up from the floor), so 6; a 5-degree turn gives ~46.
EPI_MIN_MRAD = 6.0  # a camera is off when the mean |offset| of its pairs exceeds this (radians x 1e3) ...
EPI_RATIO = 3.0  # ... and this many times that of the pairs without it
EPI_MIN_SAMPLES = 200  # keypoint pairs per camera pair in the window before any verdict


def _skew(t: np.ndarray) -> np.ndarray:
    return np.array([[0.0, -t[2], t[1]], [t[2], 0.0, -t[0]], [-t[1], t[0], 0.0]])


class EpipolarCheck:
    """Rolling per-pair signed epipolar offsets of the cameras' confident 2D keypoints (PCM
    centroids) and the camera whose pairs are off while the others agree, if any."""

    def __init__(self, rig: Rig, window: int = 100) -> None:
        self.rig = rig
        C = len(rig)
        self.pairs = np.array([(i, j) for i in range(C) for j in range(i + 1, C)], dtype=np.intp).reshape(-1, 2)
        # essential matrices x_j^T E x_i = 0 on normalized coordinates (X_j = R X_i + t)
        E = []
        for i, j in self.pairs:
            R = rig[j].R @ rig[i].R.T
            E.append(_skew(rig[j].t - R @ rig[i].t) @ R)
        self.E = np.array(E).reshape(-1, 3, 3)
        self.sums: deque[np.ndarray] = deque(maxlen=window)
        self.counts: deque[np.ndarray] = deque(maxlen=window)

    def add(self, pcm: PcmViews) -> None:
        """One frame set's keypoints (a frame set with the subject tracked: one person)."""
        if len(self.pairs) == 0:
            return
        uv, w = camera_keypoints(pcm, len(self.rig))  # (C, J, 2), (C, J)
        conf = w >= MIN_PEAK
        x = np.ones(uv.shape[:2] + (3,))
        for c in range(len(self.rig)):  # cv2 undistorts one camera at a time
            if conf[c].any():
                x[c, conf[c], :2] = self.rig[c].undistort_pixels(uv[c, conf[c]])
        I, J = self.pairs[:, 0], self.pairs[:, 1]
        lines = np.einsum("pab,pkb->pka", self.E, x[I])  # (P, K, 3): epipolar lines in camera j
        d = (x[J] * lines).sum(axis=-1) / np.maximum(np.linalg.norm(lines[..., :2], axis=-1), 1e-12)
        ok = conf[I] & conf[J] & np.isfinite(d)
        self.sums.append(np.where(ok, d, 0.0).sum(axis=1))
        self.counts.append(ok.sum(axis=1))

    def offsets_mrad(self) -> np.ndarray | None:
        """(P,) mean signed offset per pair in milliradians, None before EPI_MIN_SAMPLES each."""
        if not self.counts:
            return None
        n = np.sum(self.counts, axis=0)
        if len(n) == 0 or n.min() < EPI_MIN_SAMPLES:
            return None
        return 1e3 * np.sum(self.sums, axis=0) / n

    def odd(self) -> tuple[str, float, float] | None:
        """(camera, mean |offset| of its pairs in mrad, that of the other pairs) when one camera's
        pairs are off and the others agree; needs 3 cameras."""
        m = self.offsets_mrad()
        if m is None or len(self.rig) < 3:
            return None
        m = np.abs(m)
        mine = (self.pairs[:, :, None] == np.arange(len(self.rig))).any(axis=1)  # (P, C)
        per = (m[:, None] * mine).sum(axis=0) / mine.sum(axis=0)
        c = int(np.argmax(per))
        others = float(m[~mine[:, c]].mean())
        if per[c] >= EPI_MIN_MRAD and per[c] >= EPI_RATIO * max(others, 0.3):
            return self.rig[c].name, float(per[c]), others
        return None


# ------------------------------------------------------------------ images a camera delivers
UNIFORM_STD = 2.0  # grey levels: a sampled image flatter than this shows nothing (lens cap, dark, saturated)
SAMPLE_STEP = 16  # every 16th pixel of every 16th row: ~0.1 ms on a 1920x1080 image


def blind_cameras(pcm: PcmViews) -> set[int]:
    """Camera indices whose views in this frame set carry no usable heatmap channel (all absent:
    the PCM message's "no information", or dropped as invalid) while another camera's views carry
    some. One such frame set is normal (a person at the image edge); a camera that stays blind
    while the others track is covered, turned away, or its CNN is failing."""
    cam = np.asarray(pcm.camera, dtype=np.intp)
    seeing = np.asarray(pcm.valid, bool).any(axis=1) if cam.size else np.zeros(0, bool)
    seen_by = {int(c) for c in cam[seeing]}
    return {int(c) for c in np.unique(cam)} - seen_by if seen_by else set()


class BlindCameras:
    """How long each camera has been blind (blind_cameras) while the subject is tracked."""

    def __init__(self, warn_after_s: float = 1.0) -> None:
        self.warn_after_s = warn_after_s
        self.since: dict[int, float] = {}  # camera index -> time it was first seen blind

    def update(self, pcm: PcmViews, tracking: bool, now: float) -> dict[int, float]:
        """Camera index -> seconds blind, for the cameras blind for at least warn_after_s (a
        camera that sees again, or a frame set without tracking, resets its clock); `now`: the
        frame set's capture time, seconds."""
        blind = blind_cameras(pcm) if tracking else set()
        self.since = {c: self.since.get(c, now) for c in blind}
        return {c: now - t for c, t in sorted(self.since.items()) if now - t >= self.warn_after_s}


def image_problem(image: np.ndarray, width: int, height: int) -> str:
    """Why a camera image cannot go to the CNN ("" when it can): a size other than the one the
    rig was calibrated at (the CNN's crops and the rays would be computed with the wrong
    intrinsics: silently wrong markers), or an image without contrast (all black, all white,
    one grey), in which the CNN can find nobody."""
    h, w = image.shape[:2]
    if (w, h) != (int(width), int(height)):
        return f"image {w}x{h}, the rig is calibrated at {int(width)}x{int(height)}"
    sample = image[::SAMPLE_STEP, ::SAMPLE_STEP]
    if sample.size == 0:
        return "empty image"
    std = float(sample.std())
    if std < UNIFORM_STD:
        mean = float(sample.mean())
        kind = "black" if mean < 16 else "white" if mean > 239 else "one grey level"
        return f"image all {kind} (mean {mean:.0f}, std {std:.1f})"
    return ""
