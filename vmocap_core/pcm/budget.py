"""The CNN budget of the tracking configuration: graph rewrites that make BlazePose cheaper
without retraining, applied in memory where the model is loaded (no cache file changes).

- `resize_input(model, size)`: run the network on size x size crops instead of 256 x 256. The
  convolutions are size-agnostic; what is not: the input shape, the decoder's bilinear upsampling
  (Resize `sizes` in the float graph, the two interpolation matrices per Resize in the int8 graph,
  int8_prepare.prepare), and the presence head, whose 2 x 2 valid convolution after two 2 x 2 max
  pools needs the 8 x 8 bottom of a 256 crop. Its branch input is resampled bilinearly to the
  native 8 x 8 (the head then sees the same layout it was trained on). Heatmaps come out at
  size / 4 cells, still stride 4 in network pixels, so the crop -> map affine is unchanged.
- `slim_conv(model, tensor, channels)`: the convolution producing `tensor` computes only
  `channels` (the lattice search reads 25 of BlazePose's 39 heatmap channels).

The size is chosen by `input_size(...)`: the argument, else $VMOCAP_PCM_INPUT, else
DEFAULT_INPUT_SIZE; 256 is the network as published (docs/cnn_budget.md has the measurements).
"""

from __future__ import annotations

import os

import numpy as np
import onnx
from onnx import helper, numpy_helper, shape_inference

from ..errors import ModelError
from .int8_prepare import linear_resize_matrix

NATIVE_SIZE = 256
STEP = 32  # five stride-2 stages: the bottom of the encoder is size / 32 cells
INPUT_SIZES = (160, 192, 224, 256)
DEFAULT_INPUT_SIZE = 256
INPUT_ENV = "VMOCAP_PCM_INPUT"  # overrides the default input size (e.g. =256) in every process


def input_size(size: int | None = None) -> int:
    """The BlazePose input side: `size`, else $VMOCAP_PCM_INPUT, else DEFAULT_INPUT_SIZE."""
    raw = size if size is not None else os.environ.get(INPUT_ENV) or DEFAULT_INPUT_SIZE
    try:
        value = int(raw)
    except (TypeError, ValueError):
        raise ModelError(f"BlazePose input size must be one of {INPUT_SIZES}, got {raw!r}") from None
    if value not in INPUT_SIZES:
        raise ModelError(f"BlazePose input size must be one of {INPUT_SIZES}, got {value}")
    return value


def _dependencies(g: onnx.GraphProto, outputs: list[str]) -> set[int]:
    """Indices of the nodes `outputs` depend on."""
    needed, keep = set(outputs), set()
    for k in range(len(g.node) - 1, -1, -1):
        n = g.node[k]
        if any(o in needed for o in n.output):
            keep.add(k)
            needed.update(i for i in n.input if i)
    return keep


def _spatial_shapes(model: onnx.ModelProto) -> dict[str, list[int]]:
    m = shape_inference.infer_shapes(model)
    vals = [*m.graph.value_info, *m.graph.input, *m.graph.output]
    return {v.name: [d.dim_value for d in v.type.tensor_type.shape.dim] for v in vals}


def resize_input(model: onnx.ModelProto, size: int, native_branch: tuple[list[str], list[str]] | None = None) -> onnx.ModelProto:
    """Copy of a converted BlazePose graph (float or int8, NHWC input) for size x size input.

    native_branch: (outputs, apart_from): the nodes the first outputs need and the second do
    not (the presence head apart from the heatmaps) see native-size features: the tensors
    entering that branch are resampled to their native size."""
    if size == NATIVE_SIZE:
        return model
    if size % STEP:
        raise ModelError(f"input size {size} is not a multiple of {STEP}")
    out = onnx.ModelProto()
    out.CopyFrom(model)
    g = out.graph
    dims = g.input[0].type.tensor_type.shape.dim
    if [d.dim_value for d in dims[1:]] != [NATIVE_SIZE, NATIVE_SIZE, 3]:
        raise ModelError(f"expected a {NATIVE_SIZE} x {NATIVE_SIZE} x 3 input, got {[d.dim_value for d in dims]}")
    native = _spatial_shapes(model)
    scale = size / NATIVE_SIZE
    dims[1].dim_value = dims[2].dim_value = size
    inits = {t.name: t for t in g.initializer}

    def scaled(n: int) -> int:
        if (n * size) % NATIVE_SIZE:
            raise ModelError(f"a {n}-cell map does not scale to input {size}")
        return n * size // NATIVE_SIZE

    for n in g.node:
        if n.op_type == "Resize" and len(n.input) == 4 and n.input[3] in inits:
            t = inits[n.input[3]]
            sizes = numpy_helper.to_array(t)
            t.CopyFrom(numpy_helper.from_array(np.array([scaled(int(s)) for s in sizes], sizes.dtype), t.name))
        elif n.op_type == "MatMul":  # int8_prepare.prepare's Resize: x @ cols, then rows @ (...)
            for name, rows in ((n.input[1], False), (n.input[0], True)):
                if name in inits and name.endswith("_rows" if rows else "_cols"):
                    a = numpy_helper.to_array(inits[name])
                    n_out, n_in = a.shape if rows else a.shape[::-1]
                    m = linear_resize_matrix(scaled(n_in), scaled(n_out))
                    inits[name].CopyFrom(numpy_helper.from_array(m if rows else np.ascontiguousarray(m.T), name))
    if native_branch:
        _native_branch(g, *native_branch, native, scale)
    del g.value_info[:]
    for o in g.output:  # spatial output dims are stale: leave them to onnxruntime
        shape = o.type.tensor_type.shape.dim
        for d in shape[1:] if len(shape) == 4 else ():  # (batch, values) outputs keep theirs
            if d.dim_value and d.dim_value > 3:
                d.dim_param, d.dim_value = "", 0
    return out


def _native_branch(g: onnx.GraphProto, outputs: list[str], apart_from: list[str], native: dict[str, list[int]],
                   scale: float) -> None:
    """Resample the activations entering the branch of `outputs` (nodes `apart_from` does not
    need) to their native spatial size."""
    branch = _dependencies(g, outputs) - _dependencies(g, apart_from)
    produced_outside = {o for k, n in enumerate(g.node) if k not in branch for o in n.output}
    inits = {t.name for t in g.initializer}
    entering = sorted({i for k in branch for i in g.node[k].input if i in produced_outside and i not in inits})
    for t in entering:
        shape = native.get(t, [])
        if len(shape) != 4 or not all(shape[2:]):
            raise ModelError(f"cannot resample {t}: unknown native shape {shape}")
        if round(shape[2] * scale) == shape[2]:
            continue
        sizes = f"{t}_native_sizes"
        g.initializer.append(numpy_helper.from_array(np.array(shape[2:], np.int64), sizes))
        g.node.append(helper.make_node("Resize", [t, "", "", sizes], [t + "_native"], name=t + "_native", axes=[2, 3],
                                       mode="linear", coordinate_transformation_mode="half_pixel"))
        for k in branch:
            n = g.node[k]
            for j, i in enumerate(n.input):
                if i == t:
                    n.input[j] = t + "_native"
    _toposort(g)


def _toposort(g: onnx.GraphProto) -> None:
    """Order the nodes so that every input is produced before it is read."""
    ready = {i.name for i in g.input} | {t.name for t in g.initializer} | {""}
    pending, ordered = list(g.node), []
    while pending:
        rest = [n for n in pending if not all(i in ready for i in n.input)]
        done = [n for n in pending if all(i in ready for i in n.input)]
        if not done:
            raise ModelError("graph has a cycle or an unproduced input")
        for n in done:
            ready.update(n.output)
        ordered += done
        pending = rest
    del g.node[:]
    g.node.extend(ordered)


def slim_conv(model: onnx.ModelProto, tensor: str, channels: np.ndarray) -> tuple[onnx.ModelProto, np.ndarray] | None:
    """(copy whose Conv producing `tensor` computes only the distinct `channels`, the indices of
    `channels` in the new output); None when `tensor` is not a float Conv with constant weights
    read by nothing else."""
    g = model.graph
    node = next((n for n in g.node if tensor in n.output), None)
    inits = {t.name: t for t in g.initializer}
    readers = [n for n in g.node if tensor in n.input] + [o for o in g.output if o.name == tensor]
    if node is None or node.op_type != "Conv" or len(readers) != 1 or node.input[1] not in inits:
        return None
    keep = np.unique(channels)
    out = onnx.ModelProto()
    out.CopyFrom(model)
    inits = {t.name: t for t in out.graph.initializer}
    shared = {i for n in out.graph.node if n.output[0] != tensor for i in n.input}
    for name in node.input[1:3]:
        if not name or name not in inits or name in shared:
            return None
        a = numpy_helper.to_array(inits[name])
        if a.dtype != np.float32:
            return None
        inits[name].CopyFrom(numpy_helper.from_array(np.ascontiguousarray(a[keep]), name))
    for v in [v for v in out.graph.value_info if v.name == tensor]:  # its channel count changed
        out.graph.value_info.remove(v)
    return out, np.searchsorted(keep, channels)
