"""The BlazePose landmark network (pose_landmark_{full,lite}) as a PCM model, run from a model
file the caller names (blazepose.py's BlazePoseLandmark picks the file and precision for this
CPU; the self-check runs this class on the files it compares).

Input: a 256 x 256 RGB crop in [0, 1], rotated so the person is upright (crops.py).
Outputs used: `Identity_3` (1 x 64 x 64 x 39 heatmap logits: 33 landmarks + 6 auxiliary
channels; sigmoid -> our PCM), `Identity_1` (pose presence, already a probability in the
converted graph: ~1 with a person, ~0 on blank or noise images) and `Identity` (1 x 195: per
landmark x, y, z, visibility and presence logits; we read the visibility, MediaPipe's
probability that the landmark is in view and not occluded).

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
from ..keypoints import KEYPOINTS
from . import budget
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

# vmocap keypoint -> BlazePose landmark name (absent: no heatmap for it); the others keep their name
_RENAMED = {"left_hand": "left_index", "right_hand": "right_index", "left_toe": "left_foot_index",
            "right_toe": "right_foot_index"}
TO_BLAZEPOSE: dict[str, str] = {k: _RENAMED.get(k, k) for k in KEYPOINTS if _RENAMED.get(k, k) in BLAZEPOSE_NAMES}
# for each of our 25 channels, the BlazePose heatmap channel (-1: none)
CHANNEL: np.ndarray = np.array([BLAZEPOSE_NAMES.index(TO_BLAZEPOSE[k]) if k in TO_BLAZEPOSE else -1 for k in KEYPOINTS])

LANDMARK_VALUES, VISIBILITY = 5, 3  # `Identity` holds x, y, z, visibility, presence per landmark

# crop pixel (centre convention) -> heatmap cell coordinates: x = (p + 0.5) / 4
CROP_TO_MAP = np.array([[0.25, 0.0, 0.125], [0.0, 0.25, 0.125]])

VARIANTS = ("full", "lite")  # lite: `vmocap models fetch --lite`, same outputs, ~2x faster, less accurate
FILE_PRECISIONS = ("int8", "float")  # what a model file is


class BlazePoseNet(PcmModel):
    """A BlazePose landmark model file of a stated precision."""

    input_size = (256, 256)
    stride = 4.0
    channels_last = True
    rgb = True
    pixel_scale = 1.0 / 255.0
    pixel_offset = 0.0
    keypoints = np.arange(len(KEYPOINTS))
    channel_valid = CHANNEL >= 0
    output_names: tuple[str, ...] = ("pcm", "Identity_1", "Identity")  # "pcm" is added by extend_graph

    def __init__(self, path: Path | str | None = None, threads: int = DEFAULT_THREADS, variant: str = "full",
                 min_presence: float | None = None, parallel: str = DEFAULT_PARALLEL, precision: str | None = None,
                 session_config: dict[str, str] | None = None, input_size: int | None = None,
                 slim: bool = True, visibility: bool = True) -> None:
        """input_size: crop side in network pixels (budget.input_size: 256 is the published
        network, smaller sizes run the same weights on smaller crops, maps of input_size / 4);
        slim: the heatmap convolution computes only the channels used (same maps; False: all 39);
        visibility: weigh each map by the landmark's visibility (PcmModel.visibility; False: the
        heatmaps alone, without the landmark head);
        min_presence: views below it are invalid (default 0.5, MediaPipe's tracking threshold);
        parallel: "views" or "intra" (runner.py); path, precision, session_config: `model_file`."""
        if variant not in VARIANTS:
            raise ModelError(f"BlazePose variant must be one of {VARIANTS}, got {variant!r}")
        self.variant = variant
        side = budget.input_size(input_size)
        self.input_size, self.file_input_size = (side, side), (budget.NATIVE_SIZE, budget.NATIVE_SIZE)
        self.map_size = side // 4
        self.slim = bool(slim)
        self.use_visibility = bool(visibility)
        if not self.use_visibility:
            self.output_names = ("pcm", "Identity_1")
        path, self.precision, self.precision_reason, session_config = self.model_file(path, precision, session_config)
        super().__init__(path, threads, min_presence, parallel, session_config)

    def model_file(self, path: Path | str | None, precision: str | None,
                   session_config: dict[str, str] | None) -> tuple[Path | str, str, str, dict[str, str] | None]:
        """(file, its precision, why that precision, session options): here the file `path` names,
        of the precision ("int8" or "float") the caller says it is."""
        if path is None or precision not in FILE_PRECISIONS:
            raise ModelError(f"BlazePoseNet runs a named model file of a stated precision {FILE_PRECISIONS}, "
                             f"got {path!r} ({precision!r}); BlazePoseLandmark chooses one")
        return path, precision, f"{precision} requested", session_config

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
        heads = list(self.output_names[1:])  # presence (and landmark) heads, apart from the heatmaps
        out = budget.resize_input(out, self.input_size[0], (heads, ["Identity_3"]))
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
        maps, presence = outputs[:2]
        expect = (len(KEYPOINTS), self.map_size, self.map_size)
        if maps.ndim != 4 or maps.shape[1:] != expect:
            raise ModelError(f"{self.path}: heatmap output shape {maps.shape}, expected (V, *{expect})")
        pres = np.nan_to_num(presence.reshape(len(maps)).astype(np.float64), nan=0.0)
        return maps, np.clip(pres, 0.0, 1.0)

    def visibility(self, outputs: list[np.ndarray]) -> np.ndarray | None:
        if not self.use_visibility:
            return None
        head = outputs[2].reshape(len(outputs[2]), -1, LANDMARK_VALUES)
        logits = head[:, np.maximum(CHANNEL, 0), VISIBILITY].astype(np.float64)
        with np.errstate(over="ignore"):
            return np.where(CHANNEL >= 0, 1.0 / (1.0 + np.exp(-logits)), 1.0)


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
