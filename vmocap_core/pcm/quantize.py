"""Int8 BlazePose landmark model: static QDQ quantization of our converted ONNX, built offline.

`vmocap models fetch` turns `pose_landmark_full.onnx` into `pose_landmark_full_int8.onnx` with
`build()`: no images and no network, deterministic (the same bytes on every run with the pinned
onnx / onnxruntime), a few seconds. What is learnt from images lives in a committed file,
`vmocap_core/data/pcm/<model>_int8.json`, written by `calibrate()` from real crops
(`python -m vmocap_core.pcm.int8_calibration`: the Pose2Sim demo videos, detector crops):
equalization scales, activation ranges and the GPTQ rounding of the small convolutions.

Steps of `build()`:
- `prepare()` (int8_prepare.py) names the nodes, folds the explicit Pads into the next Conv and
  turns each bilinear Resize into two MatMuls with the same interpolation weights (onnxruntime's
  NCHW Resize took 0.8-0.9 ms of a crop for the 32 -> 64 upsampling; the float function is
  unchanged, heatmaps within 3e-6);
- `equalize()` (int8_equalize.py): cross-layer equalization (Nagel et al. 2019) of the residual
  streams (Conv outputs without activation joined by Adds, read only by Convs): channel c of
  every producer is scaled by s_c, the readers' input channel c by 1 / s_c, which is exact in
  float (heatmaps within 6e-5); s_c widens the narrow channels to the per-tensor uint8 range.
  The ReLU6 tensors are not rescaled: most of their channels reach the clip at 6, and scaling a
  channel past the calibrated maximum changes the float function on other images (p95 0.1
  cells on Panoptic);
- `onnxruntime.quantization.quantize_static` writes QDQ nodes (uint8 activations per tensor,
  MinMax ranges; int8 symmetric per-channel weights) for INT8_SPAN minus KEEP_FLOAT;
- GPTQ (Frantar et al. 2022, int8_gptq.py) replaces rounding to nearest for the convolutions
  with at most GPTQ_MAX_INPUTS inputs per output: each weight column is rounded in turn and its
  error pushed onto the columns not yet rounded and the bias, using the second moments of the
  layer's input on the calibration crops. The calibration file stores the resulting int8 offsets
  from onnxruntime's own rounding and the corrected biases, so the build needs no data and no
  linear algebra.

Measured (heatmap peaks as 5 x 5-weighted centroids, in 64 x 64 map cells, against the float
model on 88 real crops: 38 Panoptic detector crops, never used for calibration, and 50 Pose2Sim
frames; one single-threaded 256 x 256 crop, interleaved runs at load ~2.5):
- INT8_SPAN = Conv_6..Conv_108 (everything after the 128 x 128 stem up to the 8 x 8 encoder; the
  decoder, heatmap and presence heads stay float): 0.049 cells median, 0.35 p95 (Panoptic alone
  0.052 / 0.48); 12.0 ms per crop vs 15.8 for the previous build (16 x 16 and 8 x 8 only: 0.039 /
  0.24) and 18.0 float. Demo median reprojection error 10.6 px (`vmocap demo --mode in-process`;
  node graph 10.7) vs 11.6 with the previous build and 11.5 float: peak shifts of this size are
  below what the demo resolves (its figure moves by +-0.5 px with them, either way).
- without GPTQ (rounding to nearest; skip branch in int8 too) 0.097 / 0.61; GPTQ on the larger
  16 x 16 and 8 x 8 layers as well 0.048 / 0.32 (+110 KB of calibration file); GPTQ only on the
  128 - 32 px layers (<= 8192 weights) 0.054 / 0.40.
- the stem stays float: in int8 its 3 -> 24 convolution and 24-channel depthwise one run 2x
  slower (1.7 vs 0.8 ms each) and move the peaks most (+0.10 / +0.14 cells median each).
- KEEP_FLOAT, the 64 x 64 skip branch into the decoder (Conv_25 depthwise, Conv_27): quantizing
  it raised the p95 from 0.19 to 0.40 cells in an incremental test, and that depthwise
  convolution runs slower in int8 (0.4 vs 0.14 ms).
- EXTRA_SPANS, the presence head's 8 x 8 and 4 x 4 blocks (Conv_149..Conv_179): 5-6 % less time
  per crop, heatmaps untouched, presence of the self-check's borderline crop 0.62 (float 0.68,
  previous build 0.60). Its 2 x 2 blocks too: 13 % less time, but that presence falls to 0.13.
- what limits the accuracy now is the uint8 grid of the 24- and 32-channel residual streams at
  64 x 64 and 32 x 32 (ranges +-100..300, spread evenly over them, so no range choice helps);
  starting the int8 span at Conv_32 (32 x 32) gives 0.036 / 0.18 but only ~7 % less time than the
  previous build. Whole network in int8 (plain rounding): 0.33 / 1.7 cells, +2 px demo error.
- the 7-bit build (`weight_bits=7`, WEIGHT_GRIDS) for x86 CPUs without VNNI, the same ranges and
  equalization, GPTQ on the 7-bit grid, presence head float. On an AVX2-only AMD EPYC, native
  kernels, self-check crops: 0.075 / 0.23 cells, presence 0.025 (8-bit build there: 1.2 / 17
  cells, saturated; 7-bit rounding to nearest 0.11 / 0.33, presence head in 7-bit 0.27); 8
  Panoptic crops 0.066 / 0.41 (8-bit 0.051 / 0.49); demo 10.51 px in-process (8-bit on VNNI
  10.53); 10.6 vs 13.6 ms per crop for float.
"""

from __future__ import annotations

import base64
import hashlib
import json
import logging
import tempfile
import zlib
from pathlib import Path
from typing import Sequence

import numpy as np
import onnx
from onnx import numpy_helper

from ..errors import ModelError
from .int8_equalize import equalization_groups, equalization_scales, equalize
from .int8_gptq import conv_patches, gptq_rows, weight_scale
from .int8_prepare import prepare

QUANTIZER_VERSION = "4"  # bump when build() changes its output
DATA_DIR = Path(__file__).resolve().parents[1] / "data" / "pcm"
INPUT = "input_1"
# model -> (first, last) Conv/Add of the prepared graph quantized, in graph order (with the ReLU6
# after each): the encoder after the 128 x 128 stem, before the decoder (module doc).
INT8_SPAN: dict[str, tuple[str, str]] = {
    "pose_landmark_full": ("Conv_6", "Conv_108"),
}
# further int8 spans: the 8 x 8 and 4 x 4 part of the presence head (the branch only the presence
# score reads; the heatmaps do not depend on it). Its 2 x 2 blocks stay float (module doc).
EXTRA_SPANS: dict[str, tuple[tuple[str, str], ...]] = {
    "pose_landmark_full": (("Conv_149", "Conv_179"),),
}
# convolutions inside the span that stay float: the 64 x 64 skip branch into the decoder (module doc)
KEEP_FLOAT: dict[str, tuple[str, ...]] = {
    "pose_landmark_full": ("Conv_25", "Conv_27"),
}
# GPTQ rounding for the convolutions with at most this many inputs per output (all but the 1 x 1
# convolutions reading 384-864 channels; module doc)
GPTQ_MAX_INPUTS = 200
# Weight grids: bits -> (calibration key of the GPTQ rounding, largest integer, quantize_static's
# reduce_range, EXTRA_SPANS in int8). 7 bits (+-64) is for x86 CPUs without VNNI: their uint8 x
# int8 kernels add pairs of products in saturating 16-bit registers, and 2 * 255 * 64 = 32640
# stays below 32767 where 2 * 255 * 127 does not (selfcheck.py picks the build per CPU). Its
# presence head stays float: on 7 bits it moved the self-check's borderline crop by 0.27 (bound 0.25).
WEIGHT_GRIDS: dict[int, tuple[str, int, bool, bool]] = {8: ("gptq", 127, False, True), 7: ("gptq7", 64, True, False)}


def calibration_path(name: str) -> Path:
    return DATA_DIR / f"{name}_int8.json"


def _sha256_bytes(data: bytes) -> str:
    return hashlib.sha256(data).hexdigest()


def _encode_int8(a: np.ndarray) -> str:
    return base64.b64encode(zlib.compress(np.ascontiguousarray(a, np.int8).tobytes(), 9)).decode()


def _decode_int8(text: str, shape: Sequence[int]) -> np.ndarray:
    return np.frombuffer(zlib.decompress(base64.b64decode(text)), np.int8).reshape(shape)


def _quantize(model: onnx.ModelProto, nodes: Sequence[str], ranges: dict, reader=None,
              weight_bits: int = 8) -> onnx.ModelProto:
    """quantize_static (QDQ, uint8 activations per tensor, int8 per-channel weights on the
    WEIGHT_GRIDS grid) of `nodes` with the given MinMax ranges (or, with `reader`, ranges
    calibrated from its data)."""
    from onnxruntime.quantization import CalibrationMethod, QuantFormat, QuantType, quantize_static

    with tempfile.TemporaryDirectory(prefix="vmocap-int8-") as tmp:
        src, cache, out = Path(tmp) / "prepared.onnx", Path(tmp) / "ranges.json", Path(tmp) / "q.onnx"
        onnx.save(model, str(src))
        if reader is None:
            cache.write_text(json.dumps(ranges))
        logging.disable(logging.WARNING)  # the quantizer's generic "consider pre-processing" advice
        try:
            quantize_static(str(src), str(out), reader, quant_format=QuantFormat.QDQ, per_channel=True,
                            activation_type=QuantType.QUInt8, weight_type=QuantType.QInt8,
                            reduce_range=WEIGHT_GRIDS[weight_bits][2],
                            nodes_to_quantize=list(nodes), calibrate_method=CalibrationMethod.MinMax,
                            calibration_cache_path=str(cache))
        finally:
            logging.disable(logging.NOTSET)
        if reader is not None:
            ranges.update(json.loads(cache.read_text()))
        return onnx.load(str(out))


def _int8_weights(q: onnx.ModelProto, conv_weights: dict[str, str]) -> dict[str, onnx.TensorProto]:
    """conv name -> its int8 weight initializer in the QDQ model `q`."""
    inits = {i.name: i for i in q.graph.initializer}
    out = {}
    for conv, w in conv_weights.items():
        t = inits.get(w + "_quantized")
        if t is None:
            raise ModelError(f"{conv}: no int8 weights {w}_quantized in the quantized graph")
        out[conv] = t
    return out


# ------------------------------------------------------------------------------ build (no data)
def build(float_path: Path, dst: Path, calibration: Path | None = None, weight_bits: int = 8) -> None:
    """Write the int8 model for the float ONNX `float_path` from its committed calibration file,
    with weights on the `weight_bits` grid (WEIGHT_GRIDS)."""
    if weight_bits not in WEIGHT_GRIDS:
        raise ModelError(f"weight_bits must be one of {sorted(WEIGHT_GRIDS)}, not {weight_bits}")
    key, qmax, _, with_extra = WEIGHT_GRIDS[weight_bits]
    name = float_path.stem
    calibration = calibration or calibration_path(name)
    try:
        calib = json.loads(calibration.read_text())
    except (OSError, ValueError) as exc:
        raise ModelError(f"{calibration}: no readable int8 calibration for {name} ({exc})") from exc
    data = float_path.read_bytes()
    if calib.get("float_sha256") != _sha256_bytes(data):
        raise ModelError(f"{calibration} was calibrated on another {float_path.name} (converter changed?); "
                         "recalibrate: python -m vmocap_core.pcm.int8_calibration")
    model = prepare(onnx.load_from_string(data))
    names = {n.name for n in model.graph.node}
    missing = [n for n in calib["quantize_nodes"] if n not in names]
    if missing:
        raise ModelError(f"{calibration}: nodes {missing[:5]} are not in {float_path.name}")
    equalize(model, calib.get("equalization", {}))
    quantize = calib["quantize_nodes"] if with_extra else _without_extra(model, calib["quantize_nodes"], calib["extra_spans"])
    nodes = {n.name: n for n in model.graph.node}
    inits = {i.name: i for i in model.graph.initializer}
    if key not in calib:
        raise ModelError(f"{calibration} has no {weight_bits}-bit rounding ({key}); "
                         "recalibrate: python -m vmocap_core.pcm.int8_calibration")
    gptq = calib[key]
    for conv, entry in gptq.items():  # the biases that absorb the rounding (GPTQ's last column)
        n = nodes[conv]
        bias = np.frombuffer(base64.b64decode(entry["bias"]), np.float32)
        inits[n.input[2]].CopyFrom(numpy_helper.from_array(bias.copy(), n.input[2]))
    q = _quantize(model, quantize, calib["ranges"], weight_bits=weight_bits)
    for conv, t in _int8_weights(q, {c: nodes[c].input[1] for c in gptq}).items():
        rtn = numpy_helper.to_array(t)
        w = rtn.astype(np.int16) + _decode_int8(gptq[conv]["delta"], rtn.shape)  # GPTQ rounding
        t.CopyFrom(numpy_helper.from_array(np.clip(w, -qmax, qmax).astype(np.int8), t.name))
    q.producer_name, q.producer_version = "vmocap.pcm.quantize", QUANTIZER_VERSION
    q.doc_string = (f"int8 QDQ of {float_path.name}, {weight_bits}-bit weights "
                    f"(vmocap_core/pcm/quantize.py, {calibration.name})")
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


def _without_extra(model: onnx.ModelProto, nodes: Sequence[str], extra: Sequence[Sequence[str]]) -> list[str]:
    """`nodes` without those of the EXTRA_SPANS `extra`."""
    drop = {n for s in extra for n in span_nodes(model, s[0], s[1])}
    return [n for n in nodes if n not in drop]


def _tensor_values(model: onnx.ModelProto, x: np.ndarray, tensors: Sequence[str]):
    """Yield {tensor: value} of the float graph for each crop of x ((N, 256, 256, 3) float input)."""
    import onnxruntime as ort

    m = onnx.ModelProto()
    m.CopyFrom(model)
    have = {o.name for o in m.graph.output}
    m.graph.output.extend(onnx.helper.make_tensor_value_info(t, onnx.TensorProto.FLOAT, None) for t in tensors if t not in have)
    opts = ort.SessionOptions()
    opts.graph_optimization_level = ort.GraphOptimizationLevel.ORT_DISABLE_ALL
    sess = ort.InferenceSession(m.SerializeToString(), opts, providers=["CPUExecutionProvider"])
    for i in range(len(x)):
        yield dict(zip(tensors, sess.run(list(tensors), {INPUT: x[i : i + 1]})))


def calibrate(float_path: Path, crops: np.ndarray, span: tuple[str, str], out: Path, keep_float: Sequence[str] = (),
              extra: Sequence[tuple[str, str]] = ()) -> dict:
    """Everything build() learns from `crops` ((N, 256, 256, 3) uint8 BGR), written to the
    calibration file `out`: the equalization scales, the activation ranges of the int8 nodes
    (`span` without the `keep_float` convolutions) and the GPTQ rounding of their weights."""
    data = float_path.read_bytes()
    model = prepare(onnx.load_from_string(data))
    x = np.ascontiguousarray(crops[..., ::-1].astype(np.float32) / np.float32(255.0))
    # 1. cross-layer equalization of the residual streams (exact in float)
    groups = equalization_groups(model)
    tensors = [t for gr in groups for t in gr["tensors"]]
    low: dict[str, np.ndarray] = {}
    high: dict[str, np.ndarray] = {}
    for values in _tensor_values(model, x, tensors):
        for t, v in values.items():
            lo, hi = v.min(axis=(0, 2, 3)), v.max(axis=(0, 2, 3))
            low[t], high[t] = np.minimum(low.get(t, lo), lo), np.maximum(high.get(t, hi), hi)
    scales = equalization_scales(groups, low, high)
    equalize(model, scales)
    # 2. activation ranges (MinMax) of the int8 nodes, onnxruntime's calibrator
    drop = {c for k in keep_float for c in span_nodes(model, k, k)}
    quantize = [n for n in span_nodes(model, *span) if n not in drop]
    quantize += [n for s in extra for n in span_nodes(model, *s) if n not in drop and n not in quantize]

    from onnxruntime.quantization import CalibrationDataReader

    class Reader(CalibrationDataReader):
        def __init__(self) -> None:
            self.i = 0

        def get_next(self):
            if self.i >= len(x):
                return None
            self.i += 1
            return {INPUT: x[self.i - 1 : self.i]}

    ranges: dict = {}
    q = _quantize(model, quantize, ranges, Reader())
    # 3. GPTQ rounding of the small-input convolutions (second moments from every 2nd crop)
    nodes = {n.name: n for n in model.graph.node}
    inits = {i.name: i for i in model.graph.initializer}
    weights = {c: numpy_helper.to_array(inits[nodes[c].input[1]]) for c in quantize if nodes[c].op_type == "Conv"}
    convs = [c for c, W in weights.items() if int(np.prod(W.shape[1:])) <= GPTQ_MAX_INPUTS]
    hess: dict[str, np.ndarray] = {}
    count: dict[str, int] = {}
    for values in _tensor_values(model, x[::2], sorted({nodes[c].input[0] for c in convs})):
        for c in convs:
            P = conv_patches(values[nodes[c].input[0]].astype(np.float64), nodes[c], weights[c])
            if P.ndim == 2:
                P1 = np.concatenate([P, np.ones((len(P), 1))], 1)
                hess[c] = hess.get(c, 0.0) + P1.T @ P1
                count[c] = count.get(c, 0) + len(P)
            else:
                P1 = np.concatenate([P, np.ones(P.shape[:2] + (1,))], 2)
                hess[c] = hess.get(c, 0.0) + np.matmul(P1.transpose(0, 2, 1), P1)
                count[c] = count.get(c, 0) + P.shape[1]
    rounding = {}
    for bits, (key, qmax, _, with_extra) in WEIGHT_GRIDS.items():  # the same second moments, one rounding per grid
        grid = quantize if with_extra else _without_extra(model, quantize, extra)
        grid_q = q if bits == 8 else _quantize(model, grid, ranges, weight_bits=bits)
        grid_convs = [c for c in convs if c in grid]
        rtn = _int8_weights(grid_q, {c: nodes[c].input[1] for c in grid_convs})
        rounding[key] = {c: _gptq_conv(weights[c], numpy_helper.to_array(inits[nodes[c].input[2]]), hess[c] / count[c],
                                       numpy_helper.to_array(rtn[c]), qmax, c) for c in grid_convs}
    calib = {
        "model": float_path.name,
        "float_sha256": _sha256_bytes(data),
        "crops": f"{len(crops)} detector crops of the Pose2Sim Demo_SinglePerson videos (pose2sim==0.10.49)",
        "span": list(span),
        "keep_float": list(keep_float),
        "extra_spans": [list(s) for s in extra],
        "quantize_nodes": quantize,
        "equalization": scales,
        **rounding,
        "ranges": ranges,
    }
    out.parent.mkdir(parents=True, exist_ok=True)
    out.write_text(json.dumps(calib, indent=0, sort_keys=True) + "\n")
    return calib


def _gptq_conv(W: np.ndarray, b: np.ndarray, H: np.ndarray, rtn: np.ndarray, qmax: int, name: str) -> dict[str, str]:
    """GPTQ rounding of one convolution on the grid +-qmax, stored as the integer offsets from
    onnxruntime's rounding to nearest `rtn` and the bias that absorbs the rest."""
    O = W.shape[0]
    scale = weight_scale(W, qmax)
    if H.ndim == 2:
        qw, nb = gptq_rows(W.reshape(O, -1), b, H, scale, qmax=qmax)
    else:  # depthwise: one second-moment matrix per channel
        parts = [gptq_rows(W[o].reshape(1, -1), b[o : o + 1], H[o], scale[o : o + 1], qmax=qmax) for o in range(O)]
        qw, nb = np.concatenate([p[0] for p in parts]), np.concatenate([p[1] for p in parts])
    delta = qw.reshape(W.shape) - rtn.astype(np.int64)
    if np.abs(delta).max() > 127:
        raise ModelError(f"{name}: GPTQ moved a weight by {np.abs(delta).max()} steps")
    return {"delta": _encode_int8(delta), "bias": base64.b64encode(nb.astype(np.float32).tobytes()).decode()}
