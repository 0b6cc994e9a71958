"""Where a frame set's heatmaps come from (method.pipeline.PcmProvider): the CNN, a bag of
recorded heatmaps, or the synthetic noise model. Each takes the rig cameras' images and the
skeleton fed back from the previous frame set."""

from __future__ import annotations

import dataclasses
from pathlib import Path

import numpy as np

from ..bag import BagReader
from ..cameras.projection import Rig
from ..errors import BagError
from ..graph_config import Topics
from ..method.results import seed_of, skeleton_of
from .assembly import PcmAssembler, pcm_topics
from .census import EVERY as CENSUS_EVERY
from .views import PcmViews


class BagPcmProvider:
    """Heatmaps read from a bag's PCM topics, handed out in order, one frame set per call
    (looping): stands in for the CNN while keeping the rest of the graph real."""

    name = "bag"
    landmarks = "none"  # unknown: a config names the model that made the heatmaps

    def __init__(self, path: str | Path, rig: Rig, keypoints: np.ndarray, namespace: str = "/vmocap") -> None:
        topics = Topics(namespace)
        with BagReader(path) as reader:
            views = pcm_topics(reader.topics, topics, None)
            if not views:
                raise BagError(f"{path}: no PCM topics under {topics.ns}/pcm/")
            asm = PcmAssembler(rig, views, keypoints)
            sel = {topics.pcm(v): (v, "image") for v in views} | {topics.pcm_info(v): (v, "info") for v in views}
            self.frames: list[PcmViews] = []
            for m in reader.messages(list(sel)):
                v, kind = sel[m.topic]
                self.frames += asm.add_image(v, m.decode()) if kind == "image" else asm.add_info(v, m.decode())
            self.frames += asm.flush()
        if not self.frames:
            raise BagError(f"{path}: no complete PCM frame set")
        self._k = 0

    def infer(self, images: list[np.ndarray], cameras: np.ndarray, stamp_ns: int, feedback: np.ndarray | None) -> PcmViews:
        src = self.frames[self._k % len(self.frames)]
        self._k += 1
        return dataclasses.replace(src, stamp_ns=stamp_ns)


class SyntheticPcmProvider:
    """Heatmaps rendered from a motion clip's ground truth (vmocap_core.pcm.synthetic): the clip's
    frame at the frame set's stamp (stamp x fps, the clip played forth and back), so that PCM workers
    of different cameras render the same instant whatever frames each of them skipped; the input
    rotation follows the fed-back skeleton."""

    name = "synthetic"
    landmarks = "none"  # heatmaps drawn at the clip's joint centres

    def __init__(self, rig: Rig, motion_path: str | Path, fps: float, seed: int | None = None) -> None:
        """seed None: from the camera names, so that per-camera workers draw independent noise
        (one seed for all would give every view the same false peaks and swaps)."""
        import zlib

        from ..motion import extend, load_motion, resample
        from .synthetic import SyntheticPcmSource

        seed = zlib.crc32(",".join(rig.names).encode()) if seed is None else seed
        motion = extend(resample(load_motion(motion_path), fps), 2.0)
        self.source = SyntheticPcmSource(rig, motion.positions, motion.present, seed=seed, fps=fps)
        self.rig = rig
        self.fps = fps

    def infer(self, images: list[np.ndarray], cameras: np.ndarray, stamp_ns: int, feedback: np.ndarray | None) -> PcmViews:
        from ..method.rotation import trunk_tilt

        rot = trunk_tilt(self.rig, feedback) if feedback is not None else None
        pcm = self.source.render(self.source.looped(int(round(stamp_ns * self.fps / 1e9))), rotation=rot)
        return pcm.select(np.isin(pcm.camera, cameras), stamp_ns)


class ModelPcmProvider:
    """The CNN (vmocap_core.pcm.pipeline.BlazePosePcm): detector crops until a skeleton is fed
    back, then crops around the projected skeleton, rotated by the trunk tilt.

    binning > 1: the images come reduced that many times (REP 104 binning, e.g. JPEGs decoded
    at reduced size: projection.Camera.binned); crops are cut from them, and the views' affines
    are returned for full-resolution pixels, so everything downstream keeps the rig as it is."""

    def __init__(self, rig: Rig, model: str = "", rotation: str = "all", threads: int = 2, binning: int = 1,
                 crop_prediction: str = "rigid", census_every: int = CENSUS_EVERY, census_background: bool = False) -> None:
        from ..cameras.projection import binning_affine
        from .pipeline import BlazePosePcm

        variant = "lite" if model.endswith("lite") else "full"
        from ..method.landmarks import CNN_LANDMARKS

        self.landmarks = CNN_LANDMARKS
        self.crop_prediction = crop_prediction  # how its callers extrapolate the feedback (method/prediction.py)
        self.rig = rig
        self.binning = int(binning)
        self.seen = rig.binned(self.binning) if self.binning > 1 else rig  # the cameras the images come from
        self._to_binned = binning_affine(self.binning)
        self.pcm = BlazePosePcm(self.seen, rotation=rotation, threads=threads, variant=variant,
                                census_every=census_every, census_background=census_background)
        lm = self.pcm.landmark
        self.name = f"blazepose-{variant} {lm.precision} (rotation {rotation})" + (f", binning {self.binning}" if self.binning > 1 else "")
        self.precision, self.precision_reason = lm.precision, lm.precision_reason

    def warm_up(self) -> None:
        self.pcm.warm_up()

    def others_in_view(self) -> dict[str, int]:
        """Per camera, the people the detector last saw there who are not the subject."""
        return dict(zip(self.rig.names, (int(n) for n in self.pcm.others_in_view)))

    def close(self) -> None:
        self.pcm.close()

    def infer(self, images: list[np.ndarray], cameras: np.ndarray, stamp_ns: int, feedback: np.ndarray | None) -> PcmViews:
        full: list[np.ndarray | None] = [None] * len(self.rig)
        for c, img in zip(cameras, images):
            full[int(c)] = img
        # no skeleton fed back: the detector looks for the subject (at the seed, when one came)
        views = self.pcm.infer(full, keypoints=skeleton_of(feedback), stamp_ns=stamp_ns,
                             seed=seed_of(feedback))
        if self.binning > 1:  # binned pixel -> map, composed with full pixel -> binned pixel
            views.image_to_map = views.image_to_map @ self._to_binned
        return views


def make_model_provider(model: str, rig: Rig, rotation: str = "all", threads: int = 2, binning: int = 1,
                        crop_prediction: str = "rigid", census_every: int = CENSUS_EVERY,
                        census_background: bool = False) -> ModelPcmProvider:
    return ModelPcmProvider(rig, model, rotation, threads, binning, crop_prediction, census_every, census_background)
