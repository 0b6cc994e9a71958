"""One call per frame set: images (+ the current skeleton) -> PcmViews, the BlazePose way.

Initialization (no skeleton): the detector runs on every image (again on zoomed tiles where it
finds nobody or only a small person) and the best person per camera gives MediaPipe's crop.
Tracking: crops come from the skeleton projected into each camera, rotated by the trunk tilt (paper III-B, `rotation` mode), and the detector is not run.
Cameras where the body is not visible (or the detector finds nobody) get no view; when no
camera has one, the result has zero views (MarkerStage sees "nothing observed").
"""

from __future__ import annotations

from pathlib import Path
from typing import Sequence

import numpy as np

from ..cameras.projection import Rig
from ..errors import ModelError
from ..keypoints import INDEX, KEYPOINTS
from .blazepose import DEFAULT_ROTATION, MIN_TILT, BlazePoseLandmark, rotated_crops
from .choice import choose_subject, others_near
from .crops import Crops, crops_from_skeleton
from .detector import TILE_FRACTION, Detection, PoseDetector, nms
from .model import DEFAULT_THREADS
from .runner import DEFAULT_PARALLEL
from .views import PcmViews

PELVIS = INDEX["pelvis"]
ZOOM_BELOW = TILE_FRACTION  # detector crop side / shorter image side below which the tiles run too


class BlazePosePcm:
    """Detector + landmark model + crops for a rig.

    rotation: "lower_body" (paper, default), "all" or "none" (see blazepose.rotated_crops).
    margin: crop side / projected body extent while tracking. 1.15: the 64x64 heatmap covers
        the crop, so a tighter crop means finer cells; on the Pose2Sim demo (in-process, 100
        frame sets) 1.05/1.1/1.15/1.2/1.25/1.4 gave 11.2/11.3/11.2/11.7/12.2/12.8 px median
        reprojection, and 1.0 lost the person (limbs left the crop).
    variant: "full" (default) or "lite" (faster; `vmocap models fetch --lite`).
    precision: "int8" (default for full) or "float" (blazepose.resolve_precision; env VMOCAP_PCM_PRECISION).
    min_presence: views whose BlazePose presence is below it come out with valid=False.
    parallel: how the threads are used, "views" (default) or "intra" (runner.py).
    census_every: while tracking, the detector looks at one camera every that many frame sets
        for other people (others_in_view; 0: never, others_in_view then comes from initializations).
    """

    def __init__(
        self,
        rig: Rig,
        rotation: str = DEFAULT_ROTATION,
        threads: int = DEFAULT_THREADS,
        margin: float = 1.15,
        min_tilt: float = MIN_TILT,
        landmark_path: Path | str | None = None,
        detector_path: Path | str | None = None,
        variant: str = "full",
        min_presence: float = 0.5,
        parallel: str = DEFAULT_PARALLEL,
        precision: str | None = None,
        census_every: int = 120,
    ) -> None:
        self.rig = rig
        self.rotation = rotation
        self.margin = float(margin)
        self.min_tilt = float(min_tilt)
        self.landmark = BlazePoseLandmark(landmark_path, threads, variant, min_presence, parallel, precision)
        self._parallel = parallel
        self._detector_path = detector_path
        self._threads = threads
        self._detector: PoseDetector | None = None  # loaded on first use: tracking never needs it
        self.last_subject: np.ndarray | None = None  # (3,) pelvis of the last skeleton given to infer
        # (C,) detections that are not the subject, per camera, at the last detector run on it
        self.others_in_view = np.zeros(len(rig), dtype=int)
        self.census_every = int(census_every)
        self._census_count = 0
        rotated_crops([], np.zeros((0, 2)), [], [], rotation)  # validates the mode now

    @property
    def detector(self) -> PoseDetector:
        if self._detector is None:
            self._detector = PoseDetector(self._detector_path, self._threads, parallel=self._parallel)
        return self._detector

    def detect_people(self, images: Sequence[np.ndarray], turned: bool = True, closer: bool = True) -> list[list[Detection]]:
        """Per image (None: none), the people the detector finds, best first: the whole image,
        then (`closer`) a closer look where it found nobody or a small person, then (`turned`)
        the image turned where still nobody is found."""
        have = [c for c, im in enumerate(images) if im is not None]
        found: list[list] = [[] for _ in images]
        for c, dets in zip(have, self.detector.detect([images[c] for c in have])):
            found[c] = dets
        # A person far from the camera is a few dozen pixels tall in the detector's 224 px input:
        # missed, or found with the hips tens of pixels off (and then a loose crop). Look again
        # at twice the resolution: in tiles over the image where a view found nobody, in one
        # region around the person where it found only one smaller than that region (one extra
        # run, not six: initialization stays cheap), and keep the best of both passes.
        again = [c for c in have if closer and (not found[c] or found[c][0].crop()[1] < ZOOM_BELOW * min(images[c].shape[:2]))]
        near = [found[c][0].keypoints[0] if found[c] else None for c in again]
        for c, dets in zip(again, self.detector.detect_zoomed([images[c] for c in again], near)):
            both = found[c] + dets
            if both:
                keep = nms(np.array([d.box for d in both]), np.array([d.score for d in both]), self.detector.iou_threshold)
                found[c] = [both[i] for i in keep]
        # A body lying or upside down: where still nobody is found, look at the image turned.
        lying = [c for c in have if not found[c]] if turned else []
        for c, dets in zip(lying, self.detector.detect_turned([images[c] for c in lying])):
            found[c] = dets
        return found

    def crops_from_detector(self, images: Sequence[np.ndarray], seed: np.ndarray | None = None) -> Crops:
        """One person per image with MediaPipe's crop rule (already rotated), the same person in
        every camera when several are in view (choice.choose_subject): with `seed` (3,) (a world
        point on the wanted person, e.g. from another tracker) the person nearest to it, else the
        one seen by the most cameras. Sets others_in_view."""
        found = self.detect_people(images)
        # The same person in every camera (choice.py): the one nearest the seed, else the one
        # most cameras agree on; a camera where none of its detections is that person gets no crop.
        choice = choose_subject(self.rig, found, seed)
        self.others_in_view = choice.others
        cams = [c for c in range(len(found)) if choice.index[c] >= 0]
        return Crops.from_rectangles(cams, [found[c][choice.index[c]].crop() for c in cams])

    def _census(self, images: Sequence[np.ndarray], pelvis: np.ndarray) -> None:
        """While tracking the detector does not run for the crops: every `census_every`-th frame
        set it looks at one camera (the cameras in turn; detect_people, not turned) for people
        other than the subject, so others_in_view stays current (each camera every
        census_every x C frame sets). The crops and heatmaps do not depend on it."""
        if self.census_every <= 0:
            return
        self._census_count += 1
        have = [c for c, im in enumerate(images) if im is not None]
        if self._census_count % self.census_every or not have:
            return
        c = have[(self._census_count // self.census_every) % len(have)]
        self.others_in_view[c] = others_near(self.rig, c, self.detect_people([images[c]], turned=False)[0], pelvis)

    def crops_from_skeleton(self, keypoints: np.ndarray, tilt: np.ndarray | None = None) -> Crops:
        """Tracking crops from the skeleton (25, 3); tilt (C,) overrides the computed trunk tilt."""
        centre, side, rot, usable = crops_from_skeleton(self.rig, keypoints, tilt, self.margin)
        cams = np.flatnonzero(usable)
        return rotated_crops(cams, centre[cams], side[cams], rot[cams], self.rotation, self.min_tilt)

    def warm_up(self) -> None:
        """Load the detector and run both networks once on blank images: their first run
        allocates and picks kernels (~55 ms here), which a live graph's first frame set
        should not wait for."""
        blank = [np.zeros((c.height, c.width, 3), np.uint8) for c in self.rig]
        self.detector.detect(blank)
        n = len(self.rig)
        centre = np.array([[c.width / 2, c.height / 2] for c in self.rig])
        self.landmark.infer(blank, Crops(np.arange(n), centre, np.array([min(c.width, c.height) / 2 for c in self.rig]), np.zeros(n)))

    def infer(
        self,
        images: Sequence[np.ndarray],
        keypoints: np.ndarray | None = None,
        tilt: np.ndarray | None = None,
        stamp_ns: int = 0,
        seed: np.ndarray | None = None,
    ) -> PcmViews:
        """PCMs of one frame set: images in rig camera order (uint8 BGR or mono; None for a
        camera without a frame in this set: it gets no view).
        keypoints None: detector crops (seed picks the person, see crops_from_detector; it
        stays where to look until a skeleton comes; without one, the pelvis of the last skeleton
        given: re-initialization looks for the subject where it was last tracked, not for
        whoever else is in view)."""
        if len(images) != len(self.rig):
            raise ModelError(f"{len(images)} images for a rig of {len(self.rig)} cameras")
        if keypoints is None:
            if seed is not None:
                self.last_subject = np.asarray(seed, dtype=np.float64)
            crops = self.crops_from_detector(images, self.last_subject)
        else:
            pelvis = np.asarray(keypoints, dtype=np.float64)[PELVIS]
            if np.isfinite(pelvis).all():
                self.last_subject = pelvis
                self._census(images, pelvis)
            crops = self.crops_from_skeleton(keypoints, tilt)
            crops = crops.select(np.array([images[c] is not None for c in crops.camera], dtype=bool))
        if len(crops) == 0:
            return PcmViews.empty(len(KEYPOINTS), self.landmark.map_size, stamp_ns)
        return self.landmark.infer(images, crops, stamp_ns)

    __call__ = infer
