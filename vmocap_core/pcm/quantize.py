"""Int8 BlazePose landmark model: static QDQ quantization of our converted ONNX, built offline.

`vmocap models fetch` turns `pose_landmark_full.onnx` into `pose_landmark_full_int8.onnx` with
`build()`: no images and no network, deterministic (the same bytes on every run with the pinned
onnx / onnxruntime), a few seconds. What is learnt from images lives in a small committed file,
`vmocap_core/data/pcm/<model>_int8.json` (activation ranges), written by `calibrate()` from real
crops (`python -m vmocap_core.pcm.quantize calibrate`: the Pose2Sim demo videos, detector crops).

Steps: `prepare()` names the nodes, turns Resize(sizes, axes) into Resize(scales) (onnxruntime's
NHWC layout pass for int8 convolutions fails on `axes`) and folds the explicit Pads into the next
Conv; then `onnxruntime.quantization.quantize_static` writes QDQ nodes (uint8 activations per
tensor, MinMax ranges; int8 symmetric per-channel weights) for the nodes of INT8_SPAN only.

Why only a span (measured on 86 real crops, Pose2Sim and Panoptic, and on `vmocap demo`; heatmap
peaks as 5 x 5-weighted centroids, in 64 x 64 map cells; README): quantizing the whole network
runs the CNN ~1.5x faster but moves the peaks 0.29 cells median (1.9 at the 95th percentile) and
costs 2 px of demo reprojection error (11.2 -> 13.2 px). Most of the error comes from the
128 x 128 stem (per-tensor uint8 activations feeding depthwise kernels whose channels span
1e-2..5e2) and from the decoder, and float islands inside the stem cost more time than int8
saves there. INT8_SPAN, the encoder at 16 x 16 and 8 x 8 (~25 % of the float CNN time), moves
the peaks 0.04 cells median (0.18 p95) for ~12 % less CNN time, demo error within 0.15 px;
starting it one stage earlier (Conv_32) gave ~20 % but 0.35 cells p95 and up to +0.36 px. The
heatmap convolution (logits) and the presence branch (its flag decides whether a view is used)
stay float.
"""

from __future__ import annotations

import argparse
import hashlib
import json
import logging
import sys
import tempfile
import time
from pathlib import Path
from typing import Sequence

import numpy as np
import onnx
from onnx import numpy_helper, shape_inference

from ..errors import ModelError

QUANTIZER_VERSION = "1"  # bump when build() changes its output
DATA_DIR = Path(__file__).resolve().parents[1] / "data" / "pcm"
INPUT = "input_1"
# model -> (first, last) Conv/Add of the prepared graph quantized, in graph order (with the ReLU6
# after each): the encoder after the 128 x 128 stem, before the decoder (module doc).
INT8_SPAN: dict[str, tuple[str, str]] = {
    "pose_landmark_full": ("Conv_59", "Conv_108"),
}


def calibration_path(name: str) -> Path:
    return DATA_DIR / f"{name}_int8.json"


def _sha256_bytes(data: bytes) -> str:
    return hashlib.sha256(data).hexdigest()


# ------------------------------------------------------------------------------ graph preparation
def prepare(model: onnx.ModelProto) -> onnx.ModelProto:
    """Copy of a converted BlazePose graph ready for quantization (same function, see module doc)."""
    out = onnx.ModelProto()
    out.CopyFrom(model)
    m = shape_inference.infer_shapes(out)
    g = m.graph
    shapes = {v.name: [d.dim_value for d in v.type.tensor_type.shape.dim] for v in [*g.value_info, *g.input, *g.output]}
    inits = {i.name: i for i in g.initializer}
    consumers: dict[str, list[onnx.NodeProto]] = {}
    for n in g.node:
        for i in n.input:
            consumers.setdefault(i, []).append(n)
    drop = []
    for k, n in enumerate(g.node):
        n.name = n.name or f"{n.op_type}_{k}"
        if n.op_type == "Resize" and len(n.input) == 4 and n.input[3] in inits:
            sizes = numpy_helper.to_array(inits[n.input[3]])
            shape = shapes.get(n.input[0], [])
            axes = [list(a.ints) for a in n.attribute if a.name == "axes"]
            if len(shape) != 4 or not all(shape[2:]) or axes not in ([[2, 3]], []) or sizes.size != 2:
                raise ModelError(f"{n.name}: unexpected Resize (sizes {sizes}, input shape {shape}, axes {axes})")
            scales = np.array([1.0, 1.0, sizes[0] / shape[2], sizes[1] / shape[3]], np.float32)
            g.initializer.append(numpy_helper.from_array(scales, n.input[3] + "_scales"))
            n.input[2], n.input[3] = n.input[3] + "_scales", ""
            for a in [a for a in n.attribute if a.name == "axes"]:
                n.attribute.remove(a)
        if n.op_type == "Pad" and len(n.input) == 2 and n.input[1] in inits and len(consumers.get(n.output[0], [])) == 1:
            conv = consumers[n.output[0]][0]
            pads = numpy_helper.to_array(inits[n.input[1]])
            if conv.op_type == "Conv" and pads.size == 8 and not pads[[0, 1, 4, 5]].any() and (pads >= 0).all():
                attr = [a for a in conv.attribute if a.name == "pads"]
                old = list(attr[0].ints) if attr else [0, 0, 0, 0]
                new = [old[0] + int(pads[2]), old[1] + int(pads[3]), old[2] + int(pads[6]), old[3] + int(pads[7])]
                if attr:
                    del attr[0].ints[:]
                    attr[0].ints.extend(new)
                else:
                    conv.attribute.append(onnx.helper.make_attribute("pads", new))
                conv.input[0] = n.input[0]
                drop.append(n)
    for n in drop:
        g.node.remove(n)
    used = {i for n in g.node for i in n.input}
    for t in [t for t in g.initializer if t.name not in used]:  # the replaced sizes and pads
        g.initializer.remove(t)
    del g.value_info[:]
    return m


# ------------------------------------------------------------------------------ build (no data)
def build(float_path: Path, dst: Path, calibration: Path | None = None) -> None:
    """Write the int8 model for the float ONNX `float_path` from its committed calibration file."""
    from onnxruntime.quantization import CalibrationMethod, QuantFormat, QuantType, quantize_static

    name = float_path.stem
    calibration = calibration or calibration_path(name)
    try:
        calib = json.loads(calibration.read_text())
    except (OSError, ValueError) as exc:
        raise ModelError(f"{calibration}: no readable int8 calibration for {name} ({exc})") from exc
    data = float_path.read_bytes()
    if calib.get("float_sha256") != _sha256_bytes(data):
        raise ModelError(f"{calibration} was calibrated on another {float_path.name} (converter changed?); "
                         "recalibrate: python -m vmocap_core.pcm.quantize calibrate")
    model = prepare(onnx.load_from_string(data))
    names = {n.name for n in model.graph.node}
    missing = [n for n in calib["quantize_nodes"] if n not in names]
    if missing:
        raise ModelError(f"{calibration}: nodes {missing[:5]} are not in {float_path.name}")
    with tempfile.TemporaryDirectory(prefix="vmocap-int8-") as tmp:
        src, cache = Path(tmp) / "prepared.onnx", Path(tmp) / "ranges.json"
        onnx.save(model, str(src))
        cache.write_text(json.dumps(calib["ranges"]))
        out = Path(tmp) / dst.name
        logging.disable(logging.WARNING)  # the quantizer's generic "consider pre-processing" advice
        try:
            quantize_static(str(src), str(out), None, quant_format=QuantFormat.QDQ, per_channel=True,
                            activation_type=QuantType.QUInt8, weight_type=QuantType.QInt8,
                            nodes_to_quantize=list(calib["quantize_nodes"]), calibrate_method=CalibrationMethod.MinMax,
                            calibration_cache_path=str(cache))
        finally:
            logging.disable(logging.NOTSET)
        q = onnx.load(str(out))
    q.producer_name, q.producer_version = "vmocap.pcm.quantize", QUANTIZER_VERSION
    q.doc_string = f"int8 QDQ of {float_path.name} (vmocap_core/pcm/quantize.py, {calibration.name})"
    tmp_dst = dst.with_suffix(".onnx.tmp")
    tmp_dst.write_bytes(q.SerializeToString(deterministic=True))
    tmp_dst.replace(dst)


# ------------------------------------------------------------------------------ calibration (dev)
def span_nodes(model: onnx.ModelProto, first: str, last: str) -> list[str]:
    """Conv / Add nodes from `first` to `last` in graph order, each with the Clip (ReLU6) that
    follows it: a Conv and its activation are quantized together."""
    names = [n.name for n in model.graph.node]
    if first not in names or last not in names:
        raise ModelError(f"int8 span {first}..{last} is not in the prepared graph")
    inside = model.graph.node[names.index(first) : names.index(last) + 1]
    consumers: dict[str, list[onnx.NodeProto]] = {}
    for n in model.graph.node:
        for i in n.input:
            consumers.setdefault(i, []).append(n)
    out = []
    for n in inside:
        if n.op_type in ("Conv", "Add"):
            out.append(n.name)
            out += [c.name for c in consumers.get(n.output[0], []) if c.op_type == "Clip"]
    return list(dict.fromkeys(out))


def calibration_crops(step: int = 2) -> np.ndarray:
    """(N, 256, 256, 3) uint8 BGR crops of the person in the Pose2Sim demo videos (detector
    crops, every `step`-th frame of each camera)."""
    import cv2

    from ..calibration.datasets import pose2sim_demo
    from .blazepose import BlazePoseLandmark
    from .crops import Crops
    from .detector import PoseDetector
    from .fetch import model_dir

    demo = pose2sim_demo(fetch=True)
    if demo is None:
        raise ModelError("the Pose2Sim demo videos are needed for calibration")
    # the cached float files directly: the cache manifest names the calibration file's checksum
    det = PoseDetector(model_dir() / "pose_detection.onnx")
    lm = BlazePoseLandmark(model_dir() / "pose_landmark_full.onnx", precision="float")
    crops = []
    for video in sorted((demo / "videos").glob("cam*.mp4")):
        cap = cv2.VideoCapture(str(video))
        k = 0
        while True:
            ok, img = cap.read()
            if not ok:
                break
            if k % step == 0:
                for d in det.detect([img])[0][:1]:
                    c, side, rot = d.crop()
                    crops.append(lm.sample([img], lm.views_from_crops(Crops([0], [c], [side], [rot])))[0])
            k += 1
    return np.stack(crops)


def calibrate(float_path: Path, crops: np.ndarray, span: tuple[str, str], out: Path) -> dict:
    """Activation ranges of the `span` nodes over `crops` ((N, 256, 256, 3) uint8 BGR); writes
    the calibration file `out` that `build()` reads."""
    from onnxruntime.quantization import CalibrationDataReader, CalibrationMethod, QuantFormat, QuantType, quantize_static

    data = float_path.read_bytes()
    model = prepare(onnx.load_from_string(data))
    quantize = span_nodes(model, *span)
    x = np.ascontiguousarray(crops[..., ::-1].astype(np.float32) / np.float32(255.0))

    class Reader(CalibrationDataReader):
        def __init__(self) -> None:
            self.i = 0

        def get_next(self):
            if self.i >= len(x):
                return None
            self.i += 1
            return {INPUT: x[self.i - 1 : self.i]}

    with tempfile.TemporaryDirectory(prefix="vmocap-calib-") as tmp:
        src, cache = Path(tmp) / "prepared.onnx", Path(tmp) / "ranges.json"
        onnx.save(model, str(src))
        quantize_static(str(src), str(Path(tmp) / "q.onnx"), Reader(), quant_format=QuantFormat.QDQ, per_channel=True,
                        activation_type=QuantType.QUInt8, weight_type=QuantType.QInt8, nodes_to_quantize=quantize,
                        calibrate_method=CalibrationMethod.MinMax, calibration_cache_path=str(cache))
        ranges = json.loads(cache.read_text())
    calib = {
        "model": float_path.name,
        "float_sha256": _sha256_bytes(data),
        "crops": f"{len(crops)} detector crops of the Pose2Sim Demo_SinglePerson videos (pose2sim==0.10.49)",
        "span": list(span),
        "quantize_nodes": quantize,
        "ranges": ranges,
    }
    out.parent.mkdir(parents=True, exist_ok=True)
    out.write_text(json.dumps(calib, indent=0, sort_keys=True) + "\n")
    return calib


def main(argv: Sequence[str] | None = None) -> int:
    from . import fetch

    ap = argparse.ArgumentParser(prog="python -m vmocap_core.pcm.quantize", description=__doc__.split("\n")[0])
    sub = ap.add_subparsers(dest="cmd", required=True)
    c = sub.add_parser("calibrate", help="write vmocap_core/data/pcm/<model>_int8.json from the Pose2Sim videos")
    c.add_argument("--model", default="pose_landmark_full", choices=sorted(INT8_SPAN))
    c.add_argument("--step", type=int, default=2, help="every N-th video frame")
    args = ap.parse_args(argv)
    t0 = time.perf_counter()
    crops = calibration_crops(args.step)
    calib = calibrate(fetch.model_dir() / f"{args.model}.onnx", crops, INT8_SPAN[args.model], calibration_path(args.model))
    print(f"{calibration_path(args.model)}: {len(crops)} crops, {len(calib['quantize_nodes'])} nodes int8 "
          f"({time.perf_counter() - t0:.0f} s)")
    return 0


if __name__ == "__main__":
    sys.exit(main())
