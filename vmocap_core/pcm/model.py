"""The PCM model interface: camera images (+ where to look) in, `PcmViews` out.

A model family (BlazePose crops, OpenPose-style whole image) differs only by configuration:
network input size and layout, pixel normalization, stride of its maps, which channels are
which keypoints, and how its raw outputs become maps and a presence score. The base class does
the rest: validating images, sampling every view with one exact affine, ONE batched
onnxruntime call for all views of the frame set, and composing the image -> map affines.
"""

from __future__ import annotations

import abc
from dataclasses import dataclass
from pathlib import Path
from typing import Sequence

import cv2
import numpy as np
import onnx
import onnxruntime as ort

from ..errors import ModelError
from ..heatmaps import PcmViews, stride_affine
from ..keypoints import KEYPOINTS
from .crops import Crops, compose_affine

DEFAULT_THREADS = 2
MIN_IMAGE_PX = 16  # images smaller than this on either side cannot show a person: flagged
MAX_UPSAMPLING = 8.0  # a view magnifying its image more than this sees only a few pixels: flagged


@dataclass
class InputViews:
    """V network inputs: which camera image, and the affine image pixel -> network input pixel."""

    camera: np.ndarray  # (V,) int
    image_to_input: np.ndarray  # (V, 2, 3)
    valid: np.ndarray  # (V, len(KEYPOINTS)) bool: keypoints this view speaks for

    def __len__(self) -> int:
        return int(np.asarray(self.camera).size)


def letterbox_affine(width: int, height: int, in_w: int, in_h: int) -> np.ndarray:
    """(2, 3) affine image -> network input of a whole image scaled to fit and centred (padding
    split evenly), OpenCV pixel-centre convention (edges map to edges)."""
    s = min(in_w / width, in_h / height)
    # edge-to-edge scaling: u_edge = u + 0.5;  p + 0.5 = s * (u + 0.5) + pad
    pad_x, pad_y = (in_w - s * width) / 2, (in_h - s * height) / 2
    return np.array([[s, 0.0, 0.5 * s - 0.5 + pad_x], [0.0, s, 0.5 * s - 0.5 + pad_y]])


def check_image(image: object, index: int) -> np.ndarray:
    """A camera image as (H, W, 3) uint8 BGR (mono is expanded); ModelError otherwise."""
    if not isinstance(image, np.ndarray):
        raise ModelError(f"image {index}: expected a numpy array, got {type(image).__name__}")
    if image.dtype != np.uint8:
        raise ModelError(f"image {index}: expected uint8 pixels (bgr8/mono8), got {image.dtype}")
    if image.ndim == 2:
        image = cv2.cvtColor(image, cv2.COLOR_GRAY2BGR) if image.size else image[..., None]
    if image.ndim != 3 or image.shape[2] != 3:
        raise ModelError(f"image {index}: expected (H, W, 3) BGR or (H, W) mono, got shape {image.shape}")
    if image.shape[0] < 1 or image.shape[1] < 1:
        raise ModelError(f"image {index}: empty image {image.shape}")
    return image


def load_session(path: Path | str, threads: int = DEFAULT_THREADS, outputs: Sequence[str] | None = None) -> ort.InferenceSession:
    """An onnxruntime CPU session; `outputs` prunes the graph to what we use (BlazePose's
    segmentation decoder would otherwise cost time on every call)."""
    try:
        model = onnx.load(str(path))
    except Exception as exc:  # protobuf raises DecodeError and friends on a corrupt file
        raise ModelError(f"{path}: not a readable ONNX model ({exc}); run `vmocap models fetch`") from exc
    if outputs is not None:
        model = prune(model, outputs)
    opts = ort.SessionOptions()
    opts.intra_op_num_threads = int(threads)
    opts.inter_op_num_threads = 1
    opts.execution_mode = ort.ExecutionMode.ORT_SEQUENTIAL
    opts.graph_optimization_level = ort.GraphOptimizationLevel.ORT_ENABLE_ALL
    try:
        return ort.InferenceSession(model.SerializeToString(), opts, providers=["CPUExecutionProvider"])
    except Exception as exc:
        raise ModelError(f"{path}: onnxruntime cannot load it ({exc})") from exc


def prune(model: onnx.ModelProto, outputs: Sequence[str]) -> onnx.ModelProto:
    """Copy of `model` that computes only `outputs` (dead nodes and initializers removed)."""
    g = model.graph
    known = {o.name for o in g.output}
    missing = [o for o in outputs if o not in known]
    if missing:
        raise ModelError(f"model has no output(s) {missing} (outputs: {sorted(known)})")
    needed = set(outputs)
    keep = []
    for node in reversed(g.node):
        if any(o in needed for o in node.output):
            keep.append(node)
            needed.update(i for i in node.input if i)
    out = onnx.ModelProto()
    out.CopyFrom(model)
    del out.graph.node[:]
    out.graph.node.extend(reversed(keep))
    inits = [t for t in g.initializer if t.name in needed]
    del out.graph.initializer[:]
    out.graph.initializer.extend(inits)
    outs = [o for o in g.output if o.name in set(outputs)]
    del out.graph.output[:]
    out.graph.output.extend(outs)
    return out


class PcmModel(abc.ABC):
    """Base of every PCM model. Subclasses set the class attributes and implement `decode`."""

    input_size: tuple[int, int]  # (W, H) of the network input
    stride: float  # network input pixels per map cell
    channels_last: bool = True  # NHWC input (TFLite-born models) or NCHW
    rgb: bool = True  # the network wants RGB (our images are BGR)
    pixel_scale: float = 1.0 / 255.0  # input = pixel * scale + offset
    pixel_offset: float = 0.0
    keypoints: np.ndarray  # (J,) indices into KEYPOINTS of the output channels
    channel_valid: np.ndarray  # (J,) bool: channels the model really has (others are zero)
    output_names: tuple[str, ...]

    def __init__(self, path: Path | str, threads: int = DEFAULT_THREADS) -> None:
        self.path = Path(path)
        self.threads = int(threads)
        self.session = load_session(self.path, self.threads, self.output_names)
        inputs = self.session.get_inputs()
        if len(inputs) != 1:
            raise ModelError(f"{self.path}: expected one input, found {len(inputs)}")
        self.input_name = inputs[0].name
        shape = inputs[0].shape
        expect = (self.input_size[1], self.input_size[0], 3) if self.channels_last else (3, self.input_size[1], self.input_size[0])
        if len(shape) != 4 or tuple(shape[1:]) != expect:
            raise ModelError(f"{self.path}: input shape {shape} does not fit (batch, {expect})")
        self.batched = not isinstance(shape[0], int)  # False: one call per view (static batch 1)

    # -- to implement ----------------------------------------------------------------------
    @abc.abstractmethod
    def decode(self, outputs: list[np.ndarray]) -> tuple[np.ndarray, np.ndarray]:
        """Raw outputs (batch first) -> maps (V, J, h, w) in [0, 1] and presence (V,) in [0, 1]."""

    def default_views(self, images: Sequence[np.ndarray]) -> InputViews:
        """Views used when none are given (whole-image models); crop models raise."""
        raise ModelError(f"{type(self).__name__} needs crops (from the detector or the skeleton)")

    # -- shared pipeline -------------------------------------------------------------------
    def views_from_crops(self, crops: Crops) -> InputViews:
        w, h = self.input_size
        if w != h:
            raise ModelError(f"{type(self).__name__}: square crops need a square input, not {w}x{h}")
        return InputViews(crops.camera, crops.image_to_crop(w), crops.valid)

    def preprocess(self, images: Sequence[np.ndarray], views: InputViews) -> np.ndarray:
        """(V, H, W, 3) or (V, 3, H, W) float32 network input batch."""
        checked = [check_image(im, i) for i, im in enumerate(images)]
        cam = np.asarray(views.camera, dtype=np.intp)
        if cam.size and (cam.min() < 0 or cam.max() >= len(checked)):
            raise ModelError(f"view camera indices {cam.tolist()} out of range for {len(checked)} images")
        w, h = self.input_size
        A = np.asarray(views.image_to_input, dtype=np.float64)
        batch = np.empty((cam.size, h, w, 3), dtype=np.uint8)
        for v in range(cam.size):  # one warp per view (C-speed); batching happens in the CNN call
            cv2.warpAffine(checked[cam[v]], A[v], (w, h), dst=batch[v], flags=cv2.INTER_LINEAR,
                           borderMode=cv2.BORDER_CONSTANT, borderValue=(0, 0, 0))
        if self.rgb:
            batch = batch[..., ::-1]
        x = batch.astype(np.float32) * np.float32(self.pixel_scale) + np.float32(self.pixel_offset)
        if not self.channels_last:
            x = x.transpose(0, 3, 1, 2)
        return np.ascontiguousarray(x)

    def run(self, x: np.ndarray) -> list[np.ndarray]:
        """One onnxruntime call for the whole batch (per view only for a static-batch model)."""
        if len(x) == 0:
            raise ModelError("no views to run")
        if self.batched:
            return self.session.run(list(self.output_names), {self.input_name: x})
        parts = [self.session.run(list(self.output_names), {self.input_name: x[v : v + 1]}) for v in range(len(x))]
        return [np.concatenate([p[k] for p in parts]) for k in range(len(self.output_names))]

    def infer(self, images: Sequence[np.ndarray], views: Crops | InputViews | None = None, stamp_ns: int = 0) -> PcmViews:
        """PCMs of one frame set. images: per camera (H, W, 3) uint8 BGR or (H, W) mono;
        views: crops (crop models) or explicit input views; None = `default_views(images)`."""
        if views is None:
            views = self.default_views(images)
        elif isinstance(views, Crops):
            views = self.views_from_crops(views)
        x = self.preprocess(images, views)
        maps, presence = self.decode(self.run(x))
        A = np.asarray(views.image_to_input, dtype=np.float64)
        image_to_map = compose_affine(stride_affine(self.stride)[None], A)
        # Heatmaps look confident on anything; only the presence output (and these guards) flag
        # views that cannot contain a usable person (e.g. a 3x2 image blown up to 256x256).
        cam = np.asarray(views.camera, dtype=np.intp)
        small = np.array([min(np.shape(images[c])[:2]) < MIN_IMAGE_PX for c in cam], dtype=bool)
        magnified = np.sqrt(np.abs(np.linalg.det(A[:, :, :2]))) > MAX_UPSAMPLING
        presence = np.where(small | magnified, 0.0, presence)
        valid = np.asarray(views.valid, dtype=bool)[:, self.keypoints] & self.channel_valid[None]
        valid &= ~(small | magnified)[:, None]
        return PcmViews(
            maps=maps,
            image_to_map=image_to_map,
            camera=views.camera,
            keypoints=self.keypoints,
            valid=valid,
            presence=presence,
            stamp_ns=stamp_ns,
        ).sanitized()

    __call__ = infer


def all_keypoints_valid(n_views: int) -> np.ndarray:
    return np.ones((n_views, len(KEYPOINTS)), dtype=bool)
