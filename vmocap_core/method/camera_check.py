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
        camera that sees again, or a frame set without tracking, resets its clock)."""
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
