"""BlazePose landmark model (pose_landmark_full) as a PCM model, and the paper's input rotation.

Input: a 256 x 256 RGB crop in [0, 1], rotated so the person is upright (crops.py).
Outputs used: `Identity_3` (1 x 64 x 64 x 39 heatmap logits: 33 landmarks + 6 auxiliary
channels; sigmoid -> our PCM) and `Identity_1` (pose presence, already a probability in the
converted graph: ~1 with a person, ~0 on blank or noise images).

Heatmap cell (x, y) is centred on crop pixel (4x - 0.5, 4y - 0.5) in the OpenCV centre
convention, i.e. at (x / 64, y / 64) of the crop edge to edge (MediaPipe's own heatmap
refinement uses col / width too) -- NOT at ((x + 0.5) * 4 - 0.5) as a stride-4 block average
would be. Measured, not assumed (test_pcm_models::test_heatmap_cell_centres_by_mirror_symmetry):
feeding a crop and its exact horizontal mirror, the peaks mapped back disagree by 2 * delta where
delta is the convention's error; with the block-average convention delta = 1.94 +- 0.07 crop px
(414 keypoints, 26 real crops), with this one ~0; the model's regressed landmarks agree too.

Mapping of BlazePose's 33 landmark names to vmocap's vocabulary (`keypoints.KEYPOINTS`):
  nose 0 -> nose;  left/right_eye 2/5 -> left/right_eye (the eye centres; the inner and outer
  eye corners 1, 3, 4, 6 and the mouth corners 9, 10 are not used);  left/right_ear 7/8;
  shoulders 11/12, elbows 13/14, wrists 15/16, hips 23/24, knees 25/26, ankles 27/28,
  heels 29/30 -> same names;  left/right_foot_index 31/32 -> left/right_toe;
  left/right_index 19/20 -> left/right_hand (the index-finger landmark, the hand point farthest
  along the forearm that BlazePose localizes reliably; pinky 17/18 and thumb 21/22 unused).
  neck and pelvis have no BlazePose heatmap: their channels are zero with valid=False (the
  skeleton's neck is the shoulders' midpoint, the pelvis the hips' midpoint, handled by the IK).
BlazePose's "left" is the person's left, as ours.
"""

from __future__ import annotations

from pathlib import Path

import numpy as np
import onnx
from onnx import TensorProto, helper, numpy_helper

from ..errors import ModelError
from ..keypoints import INDEX, KEYPOINTS, LOWER_BODY
from . import budget, fetch, selfcheck
from .crops import Crops
from .model import DEFAULT_THREADS, PcmModel
from .runner import DEFAULT_PARALLEL

BLAZEPOSE_NAMES: tuple[str, ...] = (
    "nose", "left_eye_inner", "left_eye", "left_eye_outer", "right_eye_inner", "right_eye",
    "right_eye_outer", "left_ear", "right_ear", "mouth_left", "mouth_right", "left_shoulder",
    "right_shoulder", "left_elbow", "right_elbow", "left_wrist", "right_wrist", "left_pinky",
    "right_pinky", "left_index", "right_index", "left_thumb", "right_thumb", "left_hip",
    "right_hip", "left_knee", "right_knee", "left_ankle", "right_ankle", "left_heel",
    "right_heel", "left_foot_index", "right_foot_index",
)  # fmt: skip

# vmocap keypoint -> BlazePose landmark name (absent: no heatmap for it)
TO_BLAZEPOSE: dict[str, str] = {
    "nose": "nose",
    "left_eye": "left_eye",
    "right_eye": "right_eye",
    "left_ear": "left_ear",
    "right_ear": "right_ear",
    "left_shoulder": "left_shoulder",
    "right_shoulder": "right_shoulder",
    "left_elbow": "left_elbow",
    "right_elbow": "right_elbow",
    "left_wrist": "left_wrist",
    "right_wrist": "right_wrist",
    "left_hand": "left_index",
    "right_hand": "right_index",
    "left_hip": "left_hip",
    "right_hip": "right_hip",
    "left_knee": "left_knee",
    "right_knee": "right_knee",
    "left_ankle": "left_ankle",
    "right_ankle": "right_ankle",
    "left_heel": "left_heel",
    "right_heel": "right_heel",
    "left_toe": "left_foot_index",
    "right_toe": "right_foot_index",
}
# for each of our 25 channels, the BlazePose heatmap channel (-1: none)
CHANNEL: np.ndarray = np.array([BLAZEPOSE_NAMES.index(TO_BLAZEPOSE[k]) if k in TO_BLAZEPOSE else -1 for k in KEYPOINTS])

# crop pixel (centre convention) -> heatmap cell coordinates: x = (p + 0.5) / 4
CROP_TO_MAP = np.array([[0.25, 0.0, 0.125], [0.0, 0.25, 0.125]])

ROTATION_MODES = ("none", "all", "lower_body")
# Measured on real frames (test_pcm_panoptic: 5 Panoptic views turned upside down): BlazePose's
# presence drops to ~0 and its upper-body heatmaps are ~44 cm off on an unrotated inverted person,
# so the paper's variant (upper body from the unrotated view) loses the upper body, while "all"
# reproduces the upright result exactly and costs one view per camera. Hence "all" by default.
DEFAULT_ROTATION = "all"
MIN_TILT = np.deg2rad(20.0)  # below this, the upright and rotated crops nearly coincide: one view


VARIANTS = ("full", "lite")  # lite: `vmocap models fetch --lite`, same outputs, ~2x faster, less accurate
# "int8": pose_landmark_full_int8.onnx (quantize.py: the encoder after the stem in int8); "float":
# the converted model as it is; "auto" (default): int8 where the self-check passes on this CPU and
# int8 is faster (selfcheck.py), else float.
PRECISIONS = ("auto", "int8", "float")
INT8_VARIANTS = ("full",)  # lite has no int8 build
PRECISION_ENV = "VMOCAP_PCM_PRECISION"  # overrides the default precision (e.g. =float) in every process


def resolve_precision(variant: str, precision: str | None = None) -> str:
    """The requested precision: `precision` if given, else $VMOCAP_PCM_PRECISION, else "auto";
    "float" for a variant without an int8 build (unless int8 was asked for explicitly: error)."""
    import os

    chosen = precision or os.environ.get(PRECISION_ENV) or "auto"
    if chosen not in PRECISIONS:
        raise ModelError(f"BlazePose precision must be one of {PRECISIONS}, got {chosen!r}")
    if variant not in INT8_VARIANTS:
        if chosen == "int8" and precision is not None:
            raise ModelError(f"no int8 build of the {variant} landmark model (int8: {INT8_VARIANTS})")
        return "float"
    return chosen


class BlazePoseLandmark(PcmModel):
    """pose_landmark_{full,lite}.onnx from the model cache (`vmocap models fetch`)."""

    input_size = (256, 256)
    stride = 4.0
    channels_last = True
    rgb = True
    pixel_scale = 1.0 / 255.0
    pixel_offset = 0.0
    keypoints = np.arange(len(KEYPOINTS))
    channel_valid = CHANNEL >= 0
    output_names = ("pcm", "Identity_1")  # "pcm" is added by extend_graph

    def __init__(self, path: Path | str | None = None, threads: int = DEFAULT_THREADS, variant: str = "full",
                 min_presence: float | None = None, parallel: str = DEFAULT_PARALLEL, precision: str | None = None,
                 session_config: dict[str, str] | None = None, input_size: int | None = None,
                 slim: bool = True) -> None:
        """input_size: crop side in network pixels (budget.input_size: 256 is the published
        network, smaller sizes run the same weights on smaller crops, maps of input_size / 4);
        slim: the heatmap convolution computes only the channels used (same maps; False: all 39);
        min_presence: views below it are invalid (default 0.5, MediaPipe's tracking threshold);
        parallel: "views" or "intra" (runner.py); precision: "auto", "int8" or "float" (None: see
        `resolve_precision`; "auto" and "int8" run the self-check once per process, and "int8"
        raises where it fails); `path` overrides the cached model file (no self-check: the
        caller names the file and `precision` says what it is)."""
        if variant not in VARIANTS:
            raise ModelError(f"BlazePose variant must be one of {VARIANTS}, got {variant!r}")
        self.variant = variant
        side = budget.input_size(input_size)
        self.input_size, self.file_input_size = (side, side), (budget.NATIVE_SIZE, budget.NATIVE_SIZE)
        self.map_size = side // 4
        self.slim = bool(slim)
        request = resolve_precision(variant, precision)
        self.precision_reason = f"{request} requested"
        int8_build = "_int8"  # the 8-bit build unless the self-check picked another for this CPU
        if path is None and request in ("auto", "int8"):
            check = selfcheck.verdict(variant)
            if request == "int8" and not check.int8_correct:
                raise ModelError(f"precision int8 was asked for, but {check.warning}")
            request = "int8" if request == "int8" else check.precision
            self.precision_reason = check.reason
            if request == "int8":
                session_config, int8_build = check.session_config, check.int8_build
        self.precision = "float" if request == "auto" else request
        name = f"pose_landmark_{variant}" + (int8_build if self.precision == "int8" else "")
        super().__init__(path or fetch.model_path(name), threads, min_presence, parallel, session_config)

    def input_to_map(self) -> np.ndarray:
        return CROP_TO_MAP.copy()

    def extend_graph(self, model: onnx.ModelProto) -> onnx.ModelProto:
        """Output "pcm" (V, 25, 64, 64): our channels gathered from the heatmap logits, NCHW,
        sigmoid, channels without a BlazePose heatmap zeroed; computed by onnxruntime (numpy
        took ~5 ms). The gather reads the planes of the NCHW convolution behind `Identity_3`
        when the converter's NCHW -> NHWC Transpose is there (a Gather over the last axis of
        the NHWC output copies element by element: ~1.7 ms per crop)."""
        out = onnx.ModelProto()
        out.CopyFrom(model)
        g = out.graph
        source, axis, transpose = _heatmap_planes(g, "Identity_3")
        channels = np.maximum(CHANNEL, 0).astype(np.int64)
        if self.slim and not transpose:  # the heatmap convolution computes only the channels gathered
            slim = budget.slim_conv(out, source, channels)
            if slim is not None:
                out, channels = slim
                g = out.graph
        out = budget.resize_input(out, self.input_size[0], (["Identity_1"], ["Identity_3"]))
        g = out.graph
        mask = self.channel_valid.astype(np.float32).reshape(1, -1, 1, 1)
        g.initializer.extend([
            numpy_helper.from_array(channels.astype(np.int64), "_vm_channels"),
            numpy_helper.from_array(mask, "_vm_mask"),
        ])
        nodes = [helper.make_node("Gather", [source, "_vm_channels"], ["_vm_g"], axis=axis)]
        if transpose:
            nodes.append(helper.make_node("Transpose", ["_vm_g"], ["_vm_t"], perm=[0, 3, 1, 2]))
        nodes += [
            helper.make_node("Sigmoid", ["_vm_t" if transpose else "_vm_g"], ["_vm_sig"]),
            helper.make_node("Mul", ["_vm_sig", "_vm_mask"], ["pcm"]),
        ]
        g.node.extend(nodes)
        g.output.append(helper.make_tensor_value_info("pcm", TensorProto.FLOAT, ["batch", len(KEYPOINTS), self.map_size, self.map_size]))
        return out

    def decode(self, outputs: list[np.ndarray]) -> tuple[np.ndarray, np.ndarray]:
        maps, presence = outputs
        expect = (len(KEYPOINTS), self.map_size, self.map_size)
        if maps.ndim != 4 or maps.shape[1:] != expect:
            raise ModelError(f"{self.path}: heatmap output shape {maps.shape}, expected (V, *{expect})")
        pres = np.nan_to_num(presence.reshape(len(maps)).astype(np.float64), nan=0.0)
        return maps, np.clip(pres, 0.0, 1.0)


def _heatmap_planes(g: onnx.GraphProto, name: str) -> tuple[str, int, bool]:
    """(tensor, channel axis, needs NHWC -> NCHW transpose) to read the heatmaps `name` from:
    the NCHW tensor in front of the converter's final NHWC Transpose (through Identity nodes)
    when there is one, else `name` itself (NHWC)."""
    producer = {o: n for n in g.node for o in n.output}
    t = name
    while t in producer and producer[t].op_type == "Identity":
        t = producer[t].input[0]
    node = producer.get(t)
    if node is not None and node.op_type == "Transpose" and [a.ints for a in node.attribute if a.name == "perm"] == [[0, 2, 3, 1]]:
        return node.input[0], 1, False
    return name, 3, True


def rotated_crops(
    camera: np.ndarray,
    center: np.ndarray,
    side: np.ndarray,
    tilt: np.ndarray,
    mode: str = DEFAULT_ROTATION,
    min_tilt: float = MIN_TILT,
) -> Crops:
    """Crops with the paper's input image rotation (III-B) for cameras with one body each.

    tilt: (C,) trunk tilt per camera (radians, crops.py convention; e.g. tracker.trunk_tilt).
    mode "none": upright crops; "all": every keypoint from the crop rotated by the tilt;
    "lower_body" (paper): where |tilt| >= min_tilt, two views of the camera, the upright crop
    for the upper body and head and the rotated crop for keypoints.LOWER_BODY; below min_tilt
    the two crops nearly coincide, so one upright view serves all keypoints (halves the CNN
    cost while the person stands).
    """
    if mode not in ROTATION_MODES:
        raise ModelError(f"rotation mode must be one of {ROTATION_MODES}, got {mode!r}")
    camera = np.asarray(camera, dtype=np.intp).reshape(-1)
    center = np.asarray(center, dtype=np.float64).reshape(-1, 2)
    side = np.asarray(side, dtype=np.float64).reshape(-1)
    tilt = np.asarray(tilt, dtype=np.float64).reshape(-1)
    C = camera.size
    every = np.ones((C, len(KEYPOINTS)), dtype=bool)
    if mode == "none":
        return Crops(camera, center, side, np.zeros(C), every)
    if mode == "all":
        return Crops(camera, center, side, tilt, every)
    lower = np.zeros(len(KEYPOINTS), dtype=bool)
    lower[[INDEX[k] for k in LOWER_BODY]] = True
    split = np.abs(np.angle(np.exp(1j * tilt))) >= min_tilt  # wrapped to (-pi, pi]
    upright_valid = np.where(split[:, None], ~lower[None], True)
    return Crops(
        camera=np.concatenate([camera, camera[split]]),
        center=np.concatenate([center, center[split]]),
        side=np.concatenate([side, side[split]]),
        rotation=np.concatenate([np.zeros(C), tilt[split]]),
        valid=np.concatenate([upright_valid, np.broadcast_to(lower, (int(split.sum()), len(KEYPOINTS)))]),
    )
