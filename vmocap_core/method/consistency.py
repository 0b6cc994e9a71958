"""Does the skeleton sit where the images see the body? The per-frame consistency check.

The tracker follows whatever the lattice search finds near the fed-back skeleton: when the
CNN's maps go wrong (a body rolling or flipping over, crops that lost the person), the markers
follow wrong peaks or none, the IK fits them and the output looks as confident as ever. The
check asks the images instead: each keypoint of the skeleton (the first IK at the CNN's
landmarks, the feedback) is projected into every view and that view's PCM is read there,
relative to the view's own peak for the keypoint:

    r[v, j] = PCM[v, j](projection of keypoint j in view v) / max(peak[v, j], MIN_PEAK)

clipped to [0, 1]. A body where the maps are has r near 1 in most views (the PCM peaks are a
few pixels wide, so r falls to ~0.5 two to three map cells off the peak); a body on the wrong
peaks, or beside the person, reads low values; a view whose map for the keypoint is flat
(below MIN_PEAK everywhere: occluded, outside the crop, the person missed) cannot agree. A view
*agrees* on a keypoint when r >= AGREE.

The maps arrive weighed by the CNN's landmark visibility (pcm/model.py), which the lattice
search wants; the check reads them as the CNN drew them (r and the flat-map floor scaled back by
the visibility). A view that shows a hidden keypoint faintly still counts against a skeleton off
the place it draws: a skeleton sliding between two bodies keeps failing in the views that see
the other body's limbs.

Per keypoint, `confidence` = the fraction of the views that see it (in front of the camera,
a channel for it) that agree: what a controller can weigh each keypoint by (NS/keypoints'
score). Per frame, `agreement` = the mean confidence over the keypoints some view sees, and
`support` = the share of those keypoints that two cameras or more agree on: a point in space
is fixed by two rays, and a body held by one camera's maps (the others flat, or on another
limb) can drift anywhere along that camera's rays while half the views still agree. Both go
into the skeleton stage's verdict, with hysteresis (skeleton_stage.py). Cost: one bilinear
sample per view and keypoint and one maximum per map (PcmViews.peaks, computed once per
frame set).
"""

from __future__ import annotations

from collections import deque
from dataclasses import dataclass

import numpy as np

from ..cameras.projection import Rig
from ..keypoints import KEYPOINTS
from ..pcm.views import PcmViews
from .lattice import PcmSampler

N_KP = len(KEYPOINTS)
MIN_PEAK = 0.3  # a view's peak below this: its map for the keypoint is flat, it cannot agree
AGREE = 0.5  # r at or above this: the view agrees (the projection lies on its peak)


@dataclass
class ViewCheck:
    """The check of one skeleton against one frame set's PCMs."""

    confidence: np.ndarray  # (25,) fraction of the views seeing the keypoint that agree; NaN: no view sees it
    disagree: np.ndarray  # (25,) uint32 bit masks: rig cameras whose maps disagree on the keypoint
    agree: np.ndarray | None = None  # (25,) uint32 bit masks: rig cameras whose maps agree (None: not recorded)

    @property
    def agreement(self) -> float:
        """Mean confidence over the keypoints some view sees (0 when none is seen: a skeleton
        no view confirms is not confirmed)."""
        seen = np.isfinite(self.confidence)
        return float(self.confidence[seen].mean()) if seen.any() else 0.0

    @property
    def support(self) -> float | None:
        """The share of the keypoints some view sees that two cameras or more agree on (0 when
        none is seen; None for a check recorded without the agreeing cameras)."""
        if self.agree is None:
            return None
        return two_camera_share(self.agree, np.isfinite(self.confidence))

    def warning(self, status: str, min_agreement: float, min_support: float, names: list[str]) -> str:
        """The WARN of a skeleton stage whose status the check turned `status` (uncertain or
        lost): how much agrees, what it means for the output, which keypoints and cameras."""
        then = "tracking goes on without output" if status == "uncertain" else "starting over"
        support = self.support
        held = "" if support is None else f", {support:.0%} of the keypoints held by two cameras (check_min_support {min_support:.0%})"
        return (f"{status}: the skeleton disagrees with the images ({self.agreement:.0%} of the views agree per "
                f"keypoint, check_min_agreement {min_agreement:.0%}{held}), {then}; keypoints (disagreeing "
                f"cameras): {self.describe(names)}")

    def describe(self, names: list[str], threshold: float = AGREE) -> str:
        """The keypoints below `threshold` and the cameras that disagree on them, e.g.
        'left_knee (cam1, cam3), right_wrist (cam0)'."""
        if not np.isfinite(self.confidence).any():
            return "no keypoint in any view"
        parts = []
        for j in np.flatnonzero(np.nan_to_num(self.confidence, nan=1.0) < threshold):
            cams = [names[c] for c in range(len(names)) if int(self.disagree[j]) >> c & 1]
            parts.append(f"{KEYPOINTS[j]} ({', '.join(cams)})")
        return ", ".join(parts)


def two_camera_share(cameras: np.ndarray, counted: np.ndarray) -> float:
    """The share of the `counted` keypoints ((25,) bool) whose camera bit masks ((25,) uint32)
    name two cameras or more (0 when none is counted)."""
    if not counted.any():
        return 0.0
    return float((np.bitwise_count(np.asarray(cameras, np.uint32)[counted]) >= 2).mean())


def check_views(rig: Rig, pcm: PcmViews, keypoints: np.ndarray, sampler: PcmSampler | None = None) -> ViewCheck:
    """The skeleton's keypoints (25, 3) against the PCMs they should lie on (module doc)."""
    agreeing = np.zeros(N_KP, np.uint32)
    out = ViewCheck(np.full(N_KP, np.nan), np.zeros(N_KP, np.uint32), agreeing)
    kp = np.asarray(pcm.keypoints, dtype=np.intp)
    pts = np.asarray(keypoints, dtype=np.float64)[kp]
    known = np.asarray(np.isfinite(pts).all(axis=1))
    if pcm.n_views == 0 or not known.any():
        return out
    pts = np.where(known[:, None], pts, 0.0)
    sampler = sampler or PcmSampler(rig, pcm)
    value = sampler.point_values(pts).astype(np.float64)  # (V, J)
    _, peak = pcm.peaks()  # (V, J), 0 where the view has no channel
    cam = np.asarray(pcm.camera, dtype=np.intp)
    _, front = rig.project(pts)  # (C, J)
    sees = np.asarray(pcm.valid, bool) & np.asarray(front, bool)[cam] & known[None, :]
    # the maps as the CNN drew them, before the visibility weighed them (module doc); a view
    # whose visibility is 0 carries no map and cannot agree
    agree = sees & (pcm.visibility > 0) & (pcm.unweighed(value) >= AGREE * np.maximum(pcm.unweighed(peak), MIN_PEAK))
    n = sees.sum(axis=0)
    with np.errstate(invalid="ignore", divide="ignore"):
        out.confidence[kp] = np.where(n > 0, agree.sum(axis=0) / n, np.nan)
    # views of one camera (several crops) share the camera's bit
    bits = np.left_shift(np.uint32(1), cam.astype(np.uint32))[:, None]
    out.disagree[kp] = np.bitwise_or.reduce(np.where(sees & ~agree, bits, np.uint32(0)), axis=0)
    agreeing[kp] = np.bitwise_or.reduce(np.where(agree, bits, np.uint32(0)), axis=0)
    return out


class WeightTrend:
    """A track's lattice markers against its own recent past: their weight (the summed PCMs, eq.
    3) per keypoint seen, as a share of the median over the last `window` frame sets. As a body
    turns over, the CNN's maps can fade, and the crops lose the body one camera after another,
    while the tracker still follows what is left and that still agrees: the frame sets before
    the check turns uncertain drift 100-300 mm off with the weight at 0.29-0.57 of the track's.
    Relative to the track, not absolute: the weights' level differs between CNNs, bodies and
    rigs. One camera lost of four costs a quarter; a lasting change (cameras that stay off, a
    person further away) enters the median within half a window."""

    MIN_HISTORY = 10  # frame sets before the ratio is judged

    def __init__(self, window: int) -> None:
        self._history: deque[float] = deque(maxlen=window)

    def reset(self) -> None:
        self._history.clear()

    def ratio(self, weights: np.ndarray, check: ViewCheck | None, inside: np.ndarray | None = None,
              contested: np.ndarray | None = None) -> float | None:
        """This frame set's weight level (weights (25,) of its lattice markers) over the track's
        median (None: not judged: too little history, or no keypoint seen: the check's); the
        level joins the history. With `inside` (Markers.inside) the level is per view that can
        see the keypoint: a body walking out of two cameras' images at once halves the summed
        weights (eq. 3) while the maps of the views left are as strong as before. `contested`
        (25,) keypoints are left out: their weight was set to 0 for a marker another person
        found in the same place (contested.py), not because their maps faded."""
        if check is None:
            return None
        seen = np.isfinite(check.confidence)
        if contested is not None:
            seen &= ~contested
        if inside is not None:
            views = np.bitwise_count(np.asarray(inside, dtype=np.uint32))
            seen &= views > 0
            weights = weights / np.maximum(views, 1)
        if not seen.any():
            return None
        level = float(np.mean(weights[seen]))
        base = float(np.median(self._history)) if len(self._history) >= self.MIN_HISTORY else 0.0
        self._history.append(level)
        return level / base if base > 0 else None


RESUME_GAP_S = 0.1  # frame sets this far apart: tracking resumes as after a loss, confirmed first


class Verdict:
    """Frame checks -> "ok" | "uncertain" | "lost", with hysteresis (SkeletonConfig.check_*):
    one bad frame set (a view's wrong peak, a blurred limb) does not flip the status."""

    def __init__(self, min_agreement: float, uncertain_frames: int, recover_frames: int, lost_frames: int,
                 fail_agreement: float = 0.0, fail_frames: int = 2, min_support: float = 0.0,
                 fail_support: float = 0.0) -> None:
        self.min_agreement, self.fail_agreement, self.fail_frames = min_agreement, fail_agreement, fail_frames
        self.min_support, self.fail_support = min_support, fail_support
        self.uncertain_frames, self.recover_frames, self.lost_frames = uncertain_frames, recover_frames, lost_frames
        self.last: ViewCheck | None = None
        self.reset()

    def reset(self) -> None:
        self.uncertain = False
        self._bad = self._good = self._since = self._fail = 0
        self._needed = self.recover_frames  # agreeing frame sets that end the uncertain state
        self.last = None

    def doubt(self, frames: int) -> None:
        """Start uncertain (a track that just started): "ok" after `frames` agreeing frame sets,
        "lost" after lost_frames without them."""
        self.reset()
        self.uncertain, self._needed = True, frames

    @property
    def disagreed(self) -> bool:
        """The last check was bad (the hysteresis may still say "ok")."""
        return self._bad > 0

    def update(self, check: ViewCheck | None) -> str:
        if check is not None and self.min_agreement > 0:
            self.last = check
            support = -1.0 if check.support is None else check.support  # not recorded: not judged
            bad = check.agreement < self.min_agreement or 0 <= support < self.min_support
            self._bad, self._good = (self._bad + 1, 0) if bad else (0, self._good + 1)
            fail = check.agreement < self.fail_agreement or 0 <= support < self.fail_support
            self._fail = self._fail + 1 if fail else 0
            # frame sets most views contradict are not noise: no need to wait for more
            if not self.uncertain and (self._bad >= self.uncertain_frames or self._fail >= self.fail_frames):
                self.uncertain, self._since = True, 0
            elif self.uncertain and self._good >= self._needed:
                self.uncertain, self._needed = False, self.recover_frames
        if not self.uncertain:
            return "ok"
        self._since += 1
        return "lost" if self._since >= self.lost_frames else "uncertain"
