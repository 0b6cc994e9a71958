"""The method for one person, frame set by frame set: the one place the stages are composed.

    images --PCM provider--> PcmViews --MarkerStage--> Markers --SkeletonStage--> TrackResult
       ^                                   ^                                         |
       '------ crops and rotation ---------'---- first-IK keypoints of frame t-1 ----'

`Pipeline.step` is what the demo, `vmocap process`, the benchmarks and the evaluations run;
the node graph runs the same stages in its nodes (vmocap_pcm, vmocap_markers,
vmocap_skeleton) with the feedback carried by a topic, and test_graph_equivalence checks
that both give the same keypoints and joint angles.
"""

from __future__ import annotations

import time
from dataclasses import dataclass
from typing import Protocol, Sequence

import numpy as np

from ..cameras.projection import Rig
from ..pcm.views import PcmViews
from .config import PipelineConfig
from .landmarks import resolve
from .markers import MarkerStage
from .prediction import BodyPredictor
from .results import Markers, TrackResult, feedback_of
from .rotation import trunk_tilt
from .skeleton_stage import SkeletonStage


class PcmProvider(Protocol):
    """Images of a frame set (+ the fed-back skeleton) -> PcmViews: the CNN, a bag of
    heatmaps or the synthetic noise model (pcm/providers.py)."""

    def infer(self, images: list[np.ndarray], cameras: np.ndarray, stamp_ns: int,
              feedback: np.ndarray | None) -> PcmViews: ...


@dataclass
class ImageSet:
    """One synchronized frame set of camera images: `images[i]` from rig camera `cameras[i]`."""

    stamp_ns: int
    images: Sequence[np.ndarray]
    cameras: np.ndarray


@dataclass
class FrameResult:
    """Everything one step produced."""

    pcm: PcmViews
    markers: Markers
    skeleton: TrackResult
    feedback: np.ndarray | None  # what the next frame set's crops and lattice search start from

    @property
    def stamp_ns(self) -> int:
        return self.skeleton.stamp_ns

    @property
    def status(self) -> str:
        return self.skeleton.status


class Pipeline:
    """Marker stage + skeleton stage with the feedback of frame t-1 (and, given a PCM
    provider, the CNN whose crops follow that feedback)."""

    def __init__(self, rig: Rig, config: PipelineConfig | None = None, pcm: PcmProvider | None = None) -> None:
        self.rig = rig
        self.config = config or PipelineConfig()
        if pcm is not None:  # the CNN's keypoints are its landmarks, not joint centres
            self.config = self.config.replace(
                landmarks=resolve(self.config.skeleton.landmarks, getattr(pcm, "landmarks", "none")))
        self.markers = MarkerStage(rig, self.config.markers)
        self.skeleton = SkeletonStage(self.config.skeleton)
        self.pcm = pcm
        self.feedback: np.ndarray | None = None
        # the CNN's crops follow the feedback extrapolated to the frame set (prediction.py)
        self.predictor = BodyPredictor.for_provider(pcm)
        self.last: FrameResult | None = None
        self.timings: dict[str, float] = {}  # seconds of the last step per stage (pcm, markers, skeleton)

    def step(self, frame: PcmViews | ImageSet) -> FrameResult:
        t0 = time.perf_counter()
        if isinstance(frame, PcmViews):
            pcm = frame
        else:
            if self.pcm is None:
                raise TypeError("Pipeline.step got images but has no PCM provider")
            pcm = self.pcm.infer(list(frame.images), frame.cameras, frame.stamp_ns, self.predictor.predict(frame.stamp_ns))
        t1 = time.perf_counter()
        markers = self.markers.step(pcm)
        t2 = time.perf_counter()
        result = self.skeleton.step(markers)
        self.feedback = feedback_of(result)
        self.predictor.update(result.feedback_stamp, self.feedback)
        self.markers.feedback(self.feedback)
        self.timings = {"pcm": t1 - t0, "markers": t2 - t1, "skeleton": time.perf_counter() - t2}
        self.last = FrameResult(pcm, markers, result, self.feedback)
        return self.last

    def tilt(self) -> np.ndarray:
        """Per-camera trunk tilt of the current skeleton (zeros while not tracking)."""
        if self.last is None or self.last.status != "tracking":
            return np.zeros(len(self.rig))
        return trunk_tilt(self.rig, self.last.skeleton.keypoints)

