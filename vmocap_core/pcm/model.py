"""The PCM model interface: camera images (+ where to look) in, `PcmViews` out.

A model family (BlazePose crops, OpenPose-style whole image) differs only by configuration:
network input size and layout, pixel normalization, stride of its maps, which channels are
which keypoints, and how its raw outputs become maps and a presence score. The base class does
the rest: validating images, sampling every view with one exact affine, running all views of
the frame set together (runner.py: one batched onnxruntime call, or the batch split over the
threads), and composing the image -> map affines.
"""

from __future__ import annotations

import abc
from dataclasses import dataclass
from pathlib import Path
from typing import Callable, Sequence

import cv2
import numpy as np
import onnx
from onnx import TensorProto, helper, numpy_helper

from ..errors import ModelError
from .crops import Crops, compose_affine
from .runner import DEFAULT_PARALLEL, Runner
from .views import PcmViews, stride_affine

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


def read_model(path: Path | str) -> onnx.ModelProto:
    try:
        return onnx.load(str(path))
    except Exception as exc:  # protobuf raises DecodeError and friends on a corrupt file
        raise ModelError(f"{path}: not a readable ONNX model ({exc}); run `vmocap models fetch`") from exc


U8_INPUT = "image_bgr8"


def with_uint8_input(model: onnx.ModelProto, rgb: bool, scale: float, offset: float, channels_last: bool) -> onnx.ModelProto:
    """Copy of a one-input model that takes the sampled crops as they are, (N, H, W, 3) uint8
    BGR, and does the cast, channel order and pixel normalization itself: onnxruntime does that
    faster than numpy and the batch handed over is 4x smaller.

    The channel swap happens on planes (NCHW): a Gather over the last axis of an NHWC tensor
    copies element by element (measured 2.9 ms per 256 x 256 crop, a fifth of the network).
    For an NHWC network the planes are transposed back; the network's own NHWC -> NCHW
    Transpose at its input then cancels against it in onnxruntime's graph optimization."""
    out = onnx.ModelProto()
    out.CopyFrom(model)
    g = out.graph
    if len(g.input) != 1:
        raise ModelError(f"expected one model input, found {len(g.input)}")
    old = g.input[0]
    dims = [d.dim_param or d.dim_value for d in old.type.tensor_type.shape.dim]
    nhwc = dims if channels_last else [dims[0], dims[2], dims[3], dims[1]]
    pre = [
        helper.make_node("Transpose", [U8_INPUT], ["_vm_planes"], perm=[0, 3, 1, 2]),
        helper.make_node("Gather", ["_vm_planes", "_vm_order"], ["_vm_c"], axis=1),
        helper.make_node("Cast", ["_vm_c"], ["_vm_f"], to=TensorProto.FLOAT),
        helper.make_node("Mul", ["_vm_f", "_vm_scale"], ["_vm_s"]),
        helper.make_node("Add", ["_vm_s", "_vm_offset"], ["_vm_nchw" if channels_last else old.name]),
    ]
    if channels_last:
        pre.append(helper.make_node("Transpose", ["_vm_nchw"], [old.name], perm=[0, 2, 3, 1]))
    order = np.array([2, 1, 0] if rgb else [0, 1, 2], dtype=np.int64)
    g.initializer.extend([
        numpy_helper.from_array(order, "_vm_order"),
        numpy_helper.from_array(np.array(scale, np.float32), "_vm_scale"),
        numpy_helper.from_array(np.array(offset, np.float32), "_vm_offset"),
    ])
    nodes = pre + list(g.node)
    del g.node[:]
    g.node.extend(nodes)
    del g.input[:]
    g.input.append(helper.make_tensor_value_info(U8_INPUT, TensorProto.UINT8, nhwc))
    return out


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
    file_input_size: tuple[int, int] | None = None  # (W, H) of the model file when extend_graph resizes it
    stride: float  # network input pixels per map cell
    channels_last: bool = True  # NHWC input (TFLite-born models) or NCHW
    rgb: bool = True  # the network wants RGB (our images are BGR)
    pixel_scale: float = 1.0 / 255.0  # input = pixel * scale + offset
    pixel_offset: float = 0.0
    keypoints: np.ndarray  # (J,) indices into KEYPOINTS of the output channels
    channel_valid: np.ndarray  # (J,) bool: channels the model really has (others are zero)
    output_names: tuple[str, ...]
    # Views whose presence is below this are marked invalid: heatmaps peak at ~0.5 on any image,
    # so a consumer that looks only at `valid` must not see them (0 = keep every view).
    min_presence: float = 0.5

    def __init__(self, path: Path | str, threads: int = DEFAULT_THREADS, min_presence: float | None = None,
                 parallel: str = DEFAULT_PARALLEL, session_config: dict[str, str] | None = None) -> None:
        """threads: CPU threads; parallel: how they are used (runner.py: "views" or "intra");
        session_config: onnxruntime session config entries (selfcheck.INT8_KERNELS)."""
        self.path = Path(path)
        self.threads = int(threads)
        if min_presence is not None:
            self.min_presence = float(min_presence)
        model = read_model(self.path)
        if len(model.graph.input) != 1:
            raise ModelError(f"{self.path}: expected one input, found {len(model.graph.input)}")
        shape = [d.dim_param or d.dim_value for d in model.graph.input[0].type.tensor_type.shape.dim]
        w, h = self.file_input_size or self.input_size
        expect = (h, w, 3) if self.channels_last else (3, h, w)
        if len(shape) != 4 or tuple(shape[1:]) != expect:
            raise ModelError(f"{self.path}: input shape {shape} does not fit (batch, {expect})")
        model = prune(self.extend_graph(model), self.output_names)
        model = with_uint8_input(model, self.rgb, self.pixel_scale, self.pixel_offset, self.channels_last)
        self.runner = Runner(model, self.threads, parallel, self.path, session_config)

    def input_to_map(self) -> np.ndarray:
        """(2, 3) affine network-input pixel -> map coordinates. Default: cell x covers input
        pixels [s x, s (x + 1)) edge to edge (`heatmaps.stride_affine`)."""
        return stride_affine(self.stride)

    def extend_graph(self, model: onnx.ModelProto) -> onnx.ModelProto:
        """Hook: append output post-processing to the graph (runs inside onnxruntime)."""
        return model

    # -- to implement ----------------------------------------------------------------------
    @abc.abstractmethod
    def decode(self, outputs: list[np.ndarray]) -> tuple[np.ndarray, np.ndarray]:
        """Raw outputs (batch first) -> maps (V, J, h, w) in [0, 1] and presence (V,) in [0, 1]."""

    def visibility(self, outputs: list[np.ndarray]) -> np.ndarray | None:
        """Raw outputs -> (V, J) the probability that each keypoint is in view and not occluded
        (None: the model does not say)."""
        return None

    def pcm(self, outputs: list[np.ndarray]) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
        """Raw outputs -> the PCMs (V, J, h, w), presence (V,) and visibility (V, J): `decode`'s
        maps, each weighed by its keypoint's visibility where the model gives one (else ones)."""
        maps, presence = self.decode(outputs)
        visible = self.visibility(outputs)
        if visible is not None:
            # A hidden landmark's heatmap is the network's guess and peaks as high as a seen one:
            # weighed by its visibility, the PCMs summed over the views (eq. 1) follow the views
            # that see the keypoint, and a keypoint hidden in every view weighs little (eq. 5).
            maps = maps * visible[:, :, None, None].astype(maps.dtype)
            return maps, presence, visible
        return maps, presence, np.ones(maps.shape[:2])

    def default_views(self, images: Sequence[np.ndarray]) -> InputViews:
        """Views used when none are given (whole-image models); crop models raise."""
        raise ModelError(f"{type(self).__name__} needs crops (from the detector or the skeleton)")

    # -- shared pipeline -------------------------------------------------------------------
    def views_from_crops(self, crops: Crops) -> InputViews:
        w, h = self.input_size
        if w != h:
            raise ModelError(f"{type(self).__name__}: square crops need a square input, not {w}x{h}")
        return InputViews(crops.camera, crops.image_to_crop(w), crops.valid)

    def sample(self, images: Sequence[np.ndarray], views: InputViews) -> np.ndarray:
        """(V, H, W, 3) uint8 BGR network-input crops: each view warped by its exact affine."""
        warp = self._warper(images, views)
        return warp(slice(0, len(views.camera)))

    def _warper(self, images: Sequence[np.ndarray], views: InputViews) -> Callable[[slice], np.ndarray]:
        """The checked images and a function that warps a slice of the views into their crops."""
        cam = np.asarray(views.camera, dtype=np.intp)
        if cam.size and (cam.min() < 0 or cam.max() >= len(images)):
            raise ModelError(f"view camera indices {cam.tolist()} out of range for {len(images)} images")
        # only the images that views look at are checked: a camera without a frame may be None
        checked = {int(c): check_image(images[c], int(c)) for c in np.unique(cam)}
        w, h = self.input_size
        A = np.asarray(views.image_to_input, dtype=np.float64)

        def warp(part: slice) -> np.ndarray:
            idx = range(cam.size)[part]
            batch = np.empty((len(idx), h, w, 3), dtype=np.uint8)
            for k, v in enumerate(idx):  # one warp per view (C-speed); batching happens in the CNN call
                cv2.warpAffine(checked[cam[v]], A[v], (w, h), dst=batch[k], flags=cv2.INTER_LINEAR,
                               borderMode=cv2.BORDER_CONSTANT, borderValue=(0, 0, 0))
            return batch

        return warp

    def normalize(self, batch: np.ndarray) -> np.ndarray:
        """What the graph's uint8 input stage computes, in numpy: the float input of the
        original network (used to feed reference implementations in tests)."""
        if self.rgb:
            batch = batch[..., ::-1]
        x = batch.astype(np.float32) * np.float32(self.pixel_scale) + np.float32(self.pixel_offset)
        return np.ascontiguousarray(x if self.channels_last else x.transpose(0, 3, 1, 2))

    def preprocess(self, images: Sequence[np.ndarray], views: InputViews) -> np.ndarray:
        """Float network input of the original model (V, H, W, 3) or (V, 3, H, W)."""
        return self.normalize(self.sample(images, views))

    def run(self, x: np.ndarray) -> list[np.ndarray]:
        """Outputs for a (V, H, W, 3) uint8 BGR batch from `sample` (runner.py: all views of
        the frame set in one call, or split over the threads)."""
        if len(x) == 0:
            raise ModelError("no views to run")
        if x.dtype != np.uint8 or x.ndim != 4:
            raise ModelError(f"run() takes the uint8 (V, H, W, 3) batch of sample(), got {x.dtype} {x.shape}")
        return self.runner.run(self.output_names, x)

    def infer(self, images: Sequence[np.ndarray], views: Crops | InputViews | None = None, stamp_ns: int = 0) -> PcmViews:
        """PCMs of one frame set. images: per camera (H, W, 3) uint8 BGR or (H, W) mono;
        views: crops (crop models) or explicit input views; None = `default_views(images)`."""
        if views is None:
            views = self.default_views(images)
        elif isinstance(views, Crops):
            views = self.views_from_crops(views)
        if len(views.camera) == 0:
            raise ModelError("no views to run")
        maps, presence, visible = self.pcm(self.runner.run_built(self.output_names, len(views.camera), self._warper(images, views)))
        A = np.asarray(views.image_to_input, dtype=np.float64)
        image_to_map = compose_affine(self.input_to_map()[None], A)
        # Heatmaps look confident on anything; only the presence output (and these guards) flag
        # views that cannot contain a usable person (e.g. a 3x2 image blown up to 256x256).
        cam = np.asarray(views.camera, dtype=np.intp)
        small = np.array([min(np.shape(images[c])[:2]) < MIN_IMAGE_PX for c in cam], dtype=bool)
        magnified = np.sqrt(np.abs(np.linalg.det(A[:, :, :2]))) > MAX_UPSAMPLING
        presence = np.where(small | magnified, 0.0, presence)
        valid = np.asarray(views.valid, dtype=bool)[:, self.keypoints] & self.channel_valid[None]
        valid &= ~(small | magnified)[:, None] & (presence >= self.min_presence)[:, None]
        return PcmViews(
            maps=maps,
            image_to_map=image_to_map,
            camera=views.camera,
            keypoints=self.keypoints,
            valid=valid,
            presence=presence,
            stamp_ns=stamp_ns,
            visibility=visible,
        ).sanitized()

    __call__ = infer

