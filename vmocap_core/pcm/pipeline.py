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
from .census import EVERY as CENSUS_EVERY
from .census import Census
from .choice import choose_subject
from .crops import TURNED_BODY_FRACTION, Crops, crops_from_skeleton
from .detector import Detection, PoseDetector
from .model import DEFAULT_THREADS
from .runner import DEFAULT_PARALLEL
from .views import PcmViews

PELVIS = INDEX["pelvis"]


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
        for other people (others_in_view; 0: never, others_in_view then comes from initializations
        and the views' `others` is unknown once those are older than census.STALE_S).
    census_background: those looks run in a low-priority thread (census.py; live graph) instead of
        inside the frame set (deterministic; `close` ends the thread).
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
        census_every: int = CENSUS_EVERY,
        census_background: bool = False,
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
        # per camera, detections that are not the subject at the last detector run on it
        self.census = Census(rig, census_every, lambda images: self.detect_people(images, turned=False),
                             census_background, self.new_detector)
        rotated_crops([], np.zeros((0, 2)), [], [], rotation)  # validates the mode now

    @property
    def others_in_view(self) -> np.ndarray:
        """(C,) people besides the subject per camera at the last detector run on it."""
        return self.census.others

    def close(self) -> None:
        self.census.close()

    @property
    def detector(self) -> PoseDetector:
        if self._detector is None:
            self._detector = PoseDetector(self._detector_path, self._threads, parallel=self._parallel)
        return self._detector

    def new_detector(self) -> PoseDetector:
        """A detector of its own, on one thread, for work beside the frame sets (background.py)."""
        return PoseDetector(self._detector_path, threads=1)

    def detect_people(self, images: Sequence[np.ndarray], turned: bool = True, closer: bool = True) -> list[list[Detection]]:
        """PoseDetector.find_people with this pipeline's detector."""
        return self.detector.find_people(images, turned, closer)

    def crops_from_detector(self, images: Sequence[np.ndarray], seed: np.ndarray | None = None,
                            stamp_ns: int = 0) -> Crops:
        """One person per image with MediaPipe's crop rule (already rotated), the same person in
        every camera when several are in view (choice.choose_subject): with `seed` (3,) (a world
        point on the wanted person, e.g. from another tracker) the person nearest to it, else the
        one seen by the most cameras. Sets others_in_view."""
        found = self.detect_people(images)
        # The same person in every camera (choice.py): the one nearest the seed, else the one
        # most cameras agree on; a camera where none of its detections is that person gets no crop.
        choice = choose_subject(self.rig, found, seed)
        self.census.found(choice.others, stamp_ns)
        cams = [c for c in range(len(found)) if choice.index[c] >= 0]
        return Crops.from_rectangles(cams, [found[c][choice.index[c]].crop() for c in cams])

    def crops_from_skeleton(self, keypoints: np.ndarray, tilt: np.ndarray | None = None,
                            turned_fraction: float = TURNED_BODY_FRACTION) -> Crops:
        """Tracking crops from the skeleton (25, 3); tilt (C,) overrides the computed trunk tilt;
        turned_fraction: the least side's for a trunk leaning from the world's up (crops.py)."""
        centre, side, rot, usable = crops_from_skeleton(self.rig, keypoints, tilt, self.margin, turned_fraction)
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
            crops = self.crops_from_detector(images, self.last_subject, stamp_ns)
        else:
            pelvis = np.asarray(keypoints, dtype=np.float64)[PELVIS]
            if np.isfinite(pelvis).all():
                self.last_subject = pelvis
                self.census.offer(images, pelvis, stamp_ns)
            crops = self.crops_from_skeleton(keypoints, tilt)
            crops = crops.select(np.array([images[c] is not None for c in crops.camera], dtype=bool))
        if len(crops) == 0:
            views = PcmViews.empty(len(KEYPOINTS), self.landmark.map_size, stamp_ns)
        else:
            views = self.landmark.infer(images, crops, stamp_ns)
        views.others = self.census.count(stamp_ns)
        return views

    __call__ = infer
