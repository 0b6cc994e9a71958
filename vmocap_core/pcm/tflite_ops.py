"""The ONNX translation of each supported TFLite operator: HANDLERS, by operator name.

A handler reads its operator's inputs and options, appends ONNX nodes to the `Graph` and binds
the output tensor with its layout (tflite_graph.py); tflite2onnx.convert() calls them in the
TFLite file's operator order. `same_pads` (TFLite SAME padding as explicit pads) also serves
tfgraph2onnx.py.
"""

from __future__ import annotations

from typing import Any, Callable

import numpy as np
import tflite
from onnx import TensorProto

from ..errors import ModelError
from .tflite_graph import NHWC_TO_NCHW, Graph, densify


def _options(op: tflite.Operator, cls: type) -> Any:  # the flatbuffer options class named by `cls`
    table = op.BuiltinOptions()
    if table is None:
        raise ModelError(f"operator without options where {cls.__name__} was expected")
    opt = cls()
    opt.Init(table.Bytes, table.Pos)
    return opt


def same_pads(in_hw: tuple[int, int], k_hw: tuple[int, int], stride: tuple[int, int], dil: tuple[int, int]) -> list[int]:
    """TFLite SAME padding as explicit ONNX pads [top, left, bottom, right] (extra at the end)."""
    before, after = [], []
    for n, k, s, d in zip(in_hw, k_hw, stride, dil):
        out = -(-n // s)
        total = max((out - 1) * s + (k - 1) * d + 1 - n, 0)
        before.append(total // 2)
        after.append(total - total // 2)
    return before + after


def _pads(padding: int, in_shape: tuple[int, ...], k_hw: tuple[int, int], stride: tuple[int, int], dil: tuple[int, int]) -> list[int]:
    if padding == tflite.Padding.VALID:
        return [0, 0, 0, 0]
    return same_pads((in_shape[1], in_shape[2]), k_hw, stride, dil)


# -- operators ----------------------------------------------------------------------------
def _conv(g: Graph, op: tflite.Operator, depthwise: bool) -> None:
    x, w, b = (int(v) for v in op.InputsAsNumpy()[:3])
    if w not in g.consts:
        raise ModelError("convolution with non-constant weights is not supported")
    opt = _options(op, tflite.DepthwiseConv2DOptions if depthwise else tflite.Conv2DOptions)
    stride = (opt.StrideH(), opt.StrideW())
    dil = (opt.DilationHFactor(), opt.DilationWFactor())
    W = g.consts[w].astype(np.float32)
    in_shape = g.shape(x)
    if depthwise:  # TFLite [1, kh, kw, C*M] -> ONNX [C*M, 1, kh, kw], one group per input channel
        weight = np.transpose(W, (3, 0, 1, 2))
        group = in_shape[3]
    else:  # TFLite [O, kh, kw, I] -> ONNX [O, I, kh, kw]
        weight = np.transpose(W, (0, 3, 1, 2))
        group = 1
    k_hw = (W.shape[1], W.shape[2])
    inputs = [g.as_nchw(x), g.const(weight, g.tname(w))]
    if b >= 0:
        inputs.append(g.const(g.consts[b].astype(np.float32), g.tname(b)))
    y = g.node(
        "Conv",
        inputs,
        kernel_shape=list(k_hw),
        strides=list(stride),
        dilations=list(dil),
        pads=_pads(opt.Padding(), in_shape, k_hw, stride, dil),
        group=group,
    )
    g.bind(int(op.Outputs(0)), g.activation(y, opt.FusedActivationFunction()), True)


def _add(g: Graph, op: tflite.Operator) -> None:
    a, b = (int(v) for v in op.InputsAsNumpy()[:2])
    opt = _options(op, tflite.AddOptions)
    out = int(op.Outputs(0))
    four_d = len(g.shape(out)) == 4
    names = []
    for i in (a, b):
        if four_d and i in g.consts and g.consts[i].ndim < 4:
            # NHWC broadcasting over the last axis: lift to 4-D before the NCHW transpose.
            c = g.consts[i].reshape((1,) * (4 - g.consts[i].ndim) + g.consts[i].shape)
            names.append(g.const(np.transpose(c, NHWC_TO_NCHW).astype(np.float32), g.tname(i)))
        elif four_d:
            names.append(g.as_nchw(i))
        else:
            names.append(g.as_plain(i))
    y = g.node("Add", names)
    g.bind(out, g.activation(y, opt.FusedActivationFunction()), four_d)


def _pad(g: Graph, op: tflite.Operator) -> None:
    x, p = (int(v) for v in op.InputsAsNumpy()[:2])
    pads = g.consts[p].astype(np.int64)  # (rank, 2) before/after in TFLite order
    out = int(op.Outputs(0))
    if len(g.shape(x)) == 4:
        pads = pads[list(NHWC_TO_NCHW)]
        xin, nchw = g.as_nchw(x), True
    else:
        xin, nchw = g.as_plain(x), False
    onnx_pads = np.concatenate([pads[:, 0], pads[:, 1]])
    g.bind(out, g.node("Pad", [xin, g.const(onnx_pads, "pads")], mode="constant"), nchw)


def _dequantize(g: Graph, op: tflite.Operator) -> None:
    x, out = int(op.Inputs(0)), int(op.Outputs(0))
    if x in g.consts:
        g.consts[out] = g.consts[x].astype(np.float32)
        return
    if g.tensor(x).Type() != tflite.TensorType.FLOAT16:
        raise ModelError("only fp16 DEQUANTIZE is supported")
    g.bind(out, g.node("Cast", [g.names[x]], to=TensorProto.FLOAT), g.nchw[x])


def _densify(g: Graph, op: tflite.Operator) -> None:
    x, out = int(op.Inputs(0)), int(op.Outputs(0))
    sp = g.tensor(x).Sparsity()
    if x not in g.consts or sp is None:
        raise ModelError("DENSIFY of a non-constant or non-sparse tensor")
    g.consts[out] = densify(g.consts[x], g.shape(out), sp)


def _depth_to_space(g: Graph, op: tflite.Operator) -> None:
    opt = _options(op, tflite.DepthToSpaceOptions)
    # TFLite's DEPTH_TO_SPACE orders the depth as (block_y, block_x, channel): ONNX mode DCR.
    y = g.node("DepthToSpace", [g.as_nchw(int(op.Inputs(0)))], blocksize=opt.BlockSize(), mode="DCR")
    g.bind(int(op.Outputs(0)), y, True)


def _resize_bilinear(g: Graph, op: tflite.Operator) -> None:
    x, size = (int(v) for v in op.InputsAsNumpy()[:2])
    opt = _options(op, tflite.ResizeBilinearOptions)
    if opt.AlignCorners():
        mode = "align_corners"
    elif opt.HalfPixelCenters():
        mode = "half_pixel"
    else:
        mode = "asymmetric"
    h, w = (int(v) for v in g.consts[size])
    sizes = g.const(np.array([h, w], dtype=np.int64), "sizes")  # spatial axes only: batch stays free
    y = g.node("Resize", [g.as_nchw(x), "", "", sizes], axes=[2, 3], mode="linear", coordinate_transformation_mode=mode)
    g.bind(int(op.Outputs(0)), y, True)


def _reshape(g: Graph, op: tflite.Operator) -> None:
    x, out = int(op.Inputs(0)), int(op.Outputs(0))
    shape = np.array(g.shape(out), dtype=np.int64)  # static shapes: the output tensor says it all
    if g.dynamic_batch:
        if shape[0] != 1:
            raise ModelError(f"RESHAPE to {shape.tolist()} does not keep a leading batch axis")
        shape[0] = -1
    g.bind(out, g.node("Reshape", [g.as_plain(x), g.const(shape, "shape")]), False)


def _concatenation(g: Graph, op: tflite.Operator) -> None:
    opt = _options(op, tflite.ConcatenationOptions)
    ins = [int(v) for v in op.InputsAsNumpy()]
    out = int(op.Outputs(0))
    rank = len(g.shape(out))
    axis = opt.Axis() % rank
    if rank == 4:
        names, axis, nchw = [g.as_nchw(i) for i in ins], NHWC_TO_NCHW.index(axis), True
    else:
        names, nchw = [g.as_plain(i) for i in ins], False
    y = g.node("Concat", names, axis=axis)
    g.bind(out, g.activation(y, opt.FusedActivationFunction()), nchw)


def _max_pool(g: Graph, op: tflite.Operator) -> None:
    x = int(op.Inputs(0))
    opt = _options(op, tflite.Pool2DOptions)
    k = (opt.FilterHeight(), opt.FilterWidth())
    s = (opt.StrideH(), opt.StrideW())
    y = g.node(
        "MaxPool", [g.as_nchw(x)], kernel_shape=list(k), strides=list(s), pads=_pads(opt.Padding(), g.shape(x), k, s, (1, 1))
    )
    g.bind(int(op.Outputs(0)), g.activation(y, opt.FusedActivationFunction()), True)


def _logistic(g: Graph, op: tflite.Operator) -> None:
    x = int(op.Inputs(0))
    four_d = len(g.shape(x)) == 4
    y = g.node("Sigmoid", [g.as_nchw(x) if four_d else g.as_plain(x)])
    g.bind(int(op.Outputs(0)), y, four_d)


HANDLERS: dict[str, Callable[[Graph, tflite.Operator], None]] = {
    "CONV_2D": lambda g, op: _conv(g, op, depthwise=False),
    "DEPTHWISE_CONV_2D": lambda g, op: _conv(g, op, depthwise=True),
    "ADD": _add,
    "PAD": _pad,
    "DEQUANTIZE": _dequantize,
    "DENSIFY": _densify,
    "DEPTH_TO_SPACE": _depth_to_space,
    "RESIZE_BILINEAR": _resize_bilinear,
    "RESHAPE": _reshape,
    "CONCATENATION": _concatenation,
    "MAX_POOL_2D": _max_pool,
    "LOGISTIC": _logistic,
}
