"""A small TFLite flatbuffer -> ONNX translator for the float operators of the BlazePose models.

Only what `pose_landmark_full.tflite` and `pose_detection.tflite` use is supported (PAD,
DEQUANTIZE (fp16), CONV_2D, DEPTHWISE_CONV_2D, DENSIFY, ADD, DEPTH_TO_SPACE, RESIZE_BILINEAR,
RESHAPE, CONCATENATION, MAX_POOL_2D, LOGISTIC, fused activations); anything else raises a
ModelError naming the operator, so a new model fails loudly instead of converting wrongly.

Layout: TFLite tensors are NHWC, ONNX convolutions are NCHW. Every 4-D activation is kept in
NCHW inside the ONNX graph and transposed back to NHWC only where TFLite semantics depend on
the memory order (RESHAPE, graph outputs), so the converted model computes exactly the same
function with the same input/output names and shapes as the TFLite file.
Constant subgraphs (DENSIFY -> DEQUANTIZE of the weights) are folded at conversion time.
"""

from __future__ import annotations

from pathlib import Path
from typing import Any, Callable

import numpy as np
import onnx
import tflite
from onnx import TensorProto, helper, numpy_helper

from ..errors import ModelError

OPSET = 18
CONVERTER_VERSION = "2"  # bump when the translation changes (invalidates cached ONNX files)

_OP_NAMES = {v: k for k, v in vars(tflite.BuiltinOperator).items() if not k.startswith("_")}
_NP_TYPES = {
    tflite.TensorType.FLOAT32: np.float32,
    tflite.TensorType.FLOAT16: np.float16,
    tflite.TensorType.INT32: np.int32,
    tflite.TensorType.INT64: np.int64,
    tflite.TensorType.UINT8: np.uint8,
    tflite.TensorType.INT8: np.int8,
}
_NHWC_TO_NCHW = (0, 3, 1, 2)
_NCHW_TO_NHWC = (0, 2, 3, 1)


def _options(op: tflite.Operator, cls: type) -> Any:  # the flatbuffer options class named by `cls`
    table = op.BuiltinOptions()
    if table is None:
        raise ModelError(f"operator without options where {cls.__name__} was expected")
    opt = cls()
    opt.Init(table.Bytes, table.Pos)
    return opt


def _index_vector(kind: int, table: Any) -> np.ndarray:
    cls = {
        tflite.SparseIndexVector.Int32Vector: tflite.Int32Vector,
        tflite.SparseIndexVector.Uint16Vector: tflite.Uint16Vector,
        tflite.SparseIndexVector.Uint8Vector: tflite.Uint8Vector,
    }.get(kind)
    if cls is None or table is None:
        raise ModelError(f"unsupported sparse index vector type {kind}")
    vec = cls()
    vec.Init(table.Bytes, table.Pos)
    return vec.ValuesAsNumpy().astype(np.int64)


def densify(values: np.ndarray, shape: tuple[int, ...], sparsity: tflite.SparsityParameters) -> np.ndarray:
    """Dense array of a TFLite sparse tensor (DENSE and CSR dimensions, no block map)."""
    if sparsity.BlockMapLength() > 0:
        raise ModelError("block-sparse TFLite tensors are not supported")
    order = sparsity.TraversalOrderAsNumpy()
    if list(order) != list(range(len(shape))):
        raise ModelError(f"sparse traversal order {list(order)} is not supported")
    # Walk the dimensions outermost first; `pos` are the linear positions reached so far
    # within the traversed prefix, `coords` the dense coordinates that go with them.
    coords = np.zeros((1, 0), dtype=np.int64)
    for d in range(len(shape)):
        meta = sparsity.DimMetadata(d)
        if meta.Format() == tflite.DimensionType.DENSE:
            n = meta.DenseSize()
            coords = np.concatenate(
                [np.repeat(coords, n, axis=0), np.tile(np.arange(n), len(coords))[:, None]], axis=1
            )
        else:  # SPARSE_CSR: segments per current position, indices along this dimension
            seg = _index_vector(meta.ArraySegmentsType(), meta.ArraySegments())
            idx = _index_vector(meta.ArrayIndicesType(), meta.ArrayIndices())
            counts = np.diff(seg)
            if counts.size != len(coords):
                raise ModelError("sparse tensor: segment count does not match the dense prefix")
            coords = np.concatenate([np.repeat(coords, counts, axis=0), idx[seg[0] : seg[-1], None]], axis=1)
    if len(coords) != values.size:
        raise ModelError(f"sparse tensor: {values.size} values for {len(coords)} positions")
    dense = np.zeros(shape, dtype=values.dtype)
    dense[tuple(coords.T)] = values.ravel()
    return dense


class _Graph:
    """Conversion state: ONNX nodes/initializers and, per TFLite tensor, its ONNX name and layout."""

    def __init__(self, model: tflite.Model, buf: bytes, dynamic_batch: bool) -> None:
        self.model = model
        self.dynamic_batch = dynamic_batch
        self.sub = model.Subgraphs(0)
        self.buf = buf
        self.nodes: list[onnx.NodeProto] = []
        self.inits: list[onnx.TensorProto] = []
        self.consts: dict[int, np.ndarray] = {}  # TFLite tensor index -> folded value (TFLite layout)
        self.names: dict[int, str] = {}  # TFLite tensor index -> ONNX value name
        self.nchw: dict[int, bool] = {}  # True: the ONNX value is the NCHW transpose of the NHWC tensor
        self._cache: dict[tuple[int, str], str] = {}
        self._uid = 0
        for i in range(self.sub.TensorsLength()):
            value = self._buffer_value(i)
            if value is not None:
                self.consts[i] = value

    # -- tensors -----------------------------------------------------------------------
    def tensor(self, i: int) -> tflite.Tensor:
        return self.sub.Tensors(i)

    def shape(self, i: int) -> tuple[int, ...]:
        return tuple(int(s) for s in self.tensor(i).ShapeAsNumpy())

    def io_shape(self, i: int) -> list[int | str]:
        shape: list[int | str] = list(self.shape(i))
        if self.dynamic_batch:
            shape[0] = "batch"
        return shape

    def tname(self, i: int) -> str:
        return self.tensor(i).Name().decode()

    def _buffer_value(self, i: int) -> np.ndarray | None:
        t = self.tensor(i)
        b = self.model.Buffers(t.Buffer())
        if b is None or b.DataLength() == 0:
            return None
        dtype = _NP_TYPES.get(t.Type())
        if dtype is None:
            raise ModelError(f"tensor {self.tname(i)}: unsupported type {t.Type()}")
        raw = b.DataAsNumpy().tobytes()
        values = np.frombuffer(raw, dtype=dtype).copy()
        if t.Sparsity() is not None:
            return values  # densified by the DENSIFY operator that consumes it
        return values.reshape(self.shape(i))

    def fresh(self, base: str) -> str:
        self._uid += 1
        return f"{base}__{self._uid}"

    def const(self, value: np.ndarray, base: str) -> str:
        name = self.fresh(base)
        self.inits.append(numpy_helper.from_array(np.ascontiguousarray(value), name))
        return name

    def node(self, op: str, inputs: list[str], outputs: list[str] | None = None, **attrs: object) -> str:
        out = outputs or [self.fresh(op)]
        self.nodes.append(helper.make_node(op, inputs, out, **attrs))
        return out[0]

    def as_nchw(self, i: int) -> str:
        """ONNX name of tensor i in NCHW order (4-D activations)."""
        if i in self.consts:
            return self.const(np.transpose(self.consts[i], _NHWC_TO_NCHW), self.tname(i))
        if self.nchw[i]:
            return self.names[i]
        key = (i, "nchw")
        if key not in self._cache:
            self._cache[key] = self.node("Transpose", [self.names[i]], perm=list(_NHWC_TO_NCHW))
        return self._cache[key]

    def as_plain(self, i: int) -> str:
        """ONNX name of tensor i in TFLite's own (NHWC) order."""
        if i in self.consts:
            return self.const(self.consts[i], self.tname(i))
        if not self.nchw[i]:
            return self.names[i]
        key = (i, "plain")
        if key not in self._cache:
            self._cache[key] = self.node("Transpose", [self.names[i]], perm=list(_NCHW_TO_NHWC))
        return self._cache[key]

    def bind(self, i: int, name: str, nchw: bool) -> None:
        self.names[i] = name
        self.nchw[i] = nchw

    def activation(self, name: str, fused: int) -> str:
        A = tflite.ActivationFunctionType
        if fused == A.NONE:
            return name
        if fused == A.RELU:
            return self.node("Relu", [name])
        if fused in (A.RELU6, A.RELU_N1_TO_1):
            lo, hi = (0.0, 6.0) if fused == A.RELU6 else (-1.0, 1.0)
            return self.node("Clip", [name, self.const(np.float32(lo), "lo"), self.const(np.float32(hi), "hi")])
        if fused == A.TANH:
            return self.node("Tanh", [name])
        raise ModelError(f"unsupported fused activation {fused}")


def _same_pads(in_hw: tuple[int, int], k_hw: tuple[int, int], stride: tuple[int, int], dil: tuple[int, int]) -> list[int]:
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
    return _same_pads((in_shape[1], in_shape[2]), k_hw, stride, dil)


# -- operators ----------------------------------------------------------------------------
def _conv(g: _Graph, op: tflite.Operator, depthwise: bool) -> None:
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


def _add(g: _Graph, op: tflite.Operator) -> None:
    a, b = (int(v) for v in op.InputsAsNumpy()[:2])
    opt = _options(op, tflite.AddOptions)
    out = int(op.Outputs(0))
    four_d = len(g.shape(out)) == 4
    names = []
    for i in (a, b):
        if four_d and i in g.consts and g.consts[i].ndim < 4:
            # NHWC broadcasting over the last axis: lift to 4-D before the NCHW transpose.
            c = g.consts[i].reshape((1,) * (4 - g.consts[i].ndim) + g.consts[i].shape)
            names.append(g.const(np.transpose(c, _NHWC_TO_NCHW).astype(np.float32), g.tname(i)))
        elif four_d:
            names.append(g.as_nchw(i))
        else:
            names.append(g.as_plain(i))
    y = g.node("Add", names)
    g.bind(out, g.activation(y, opt.FusedActivationFunction()), four_d)


def _pad(g: _Graph, op: tflite.Operator) -> None:
    x, p = (int(v) for v in op.InputsAsNumpy()[:2])
    pads = g.consts[p].astype(np.int64)  # (rank, 2) before/after in TFLite order
    out = int(op.Outputs(0))
    if len(g.shape(x)) == 4:
        pads = pads[list(_NHWC_TO_NCHW)]
        xin, nchw = g.as_nchw(x), True
    else:
        xin, nchw = g.as_plain(x), False
    onnx_pads = np.concatenate([pads[:, 0], pads[:, 1]])
    g.bind(out, g.node("Pad", [xin, g.const(onnx_pads, "pads")], mode="constant"), nchw)


def _dequantize(g: _Graph, op: tflite.Operator) -> None:
    x, out = int(op.Inputs(0)), int(op.Outputs(0))
    if x in g.consts:
        g.consts[out] = g.consts[x].astype(np.float32)
        return
    if g.tensor(x).Type() != tflite.TensorType.FLOAT16:
        raise ModelError("only fp16 DEQUANTIZE is supported")
    g.bind(out, g.node("Cast", [g.names[x]], to=TensorProto.FLOAT), g.nchw[x])


def _densify(g: _Graph, op: tflite.Operator) -> None:
    x, out = int(op.Inputs(0)), int(op.Outputs(0))
    sp = g.tensor(x).Sparsity()
    if x not in g.consts or sp is None:
        raise ModelError("DENSIFY of a non-constant or non-sparse tensor")
    g.consts[out] = densify(g.consts[x], g.shape(out), sp)


def _depth_to_space(g: _Graph, op: tflite.Operator) -> None:
    opt = _options(op, tflite.DepthToSpaceOptions)
    # TFLite's DEPTH_TO_SPACE orders the depth as (block_y, block_x, channel): ONNX mode DCR.
    y = g.node("DepthToSpace", [g.as_nchw(int(op.Inputs(0)))], blocksize=opt.BlockSize(), mode="DCR")
    g.bind(int(op.Outputs(0)), y, True)


def _resize_bilinear(g: _Graph, op: tflite.Operator) -> None:
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


def _reshape(g: _Graph, op: tflite.Operator) -> None:
    x, out = int(op.Inputs(0)), int(op.Outputs(0))
    shape = np.array(g.shape(out), dtype=np.int64)  # static shapes: the output tensor says it all
    if g.dynamic_batch:
        if shape[0] != 1:
            raise ModelError(f"RESHAPE to {shape.tolist()} does not keep a leading batch axis")
        shape[0] = -1
    g.bind(out, g.node("Reshape", [g.as_plain(x), g.const(shape, "shape")]), False)


def _concatenation(g: _Graph, op: tflite.Operator) -> None:
    opt = _options(op, tflite.ConcatenationOptions)
    ins = [int(v) for v in op.InputsAsNumpy()]
    out = int(op.Outputs(0))
    rank = len(g.shape(out))
    axis = opt.Axis() % rank
    if rank == 4:
        names, axis, nchw = [g.as_nchw(i) for i in ins], _NHWC_TO_NCHW.index(axis), True
    else:
        names, nchw = [g.as_plain(i) for i in ins], False
    y = g.node("Concat", names, axis=axis)
    g.bind(out, g.activation(y, opt.FusedActivationFunction()), nchw)


def _max_pool(g: _Graph, op: tflite.Operator) -> None:
    x = int(op.Inputs(0))
    opt = _options(op, tflite.Pool2DOptions)
    k = (opt.FilterHeight(), opt.FilterWidth())
    s = (opt.StrideH(), opt.StrideW())
    y = g.node(
        "MaxPool", [g.as_nchw(x)], kernel_shape=list(k), strides=list(s), pads=_pads(opt.Padding(), g.shape(x), k, s, (1, 1))
    )
    g.bind(int(op.Outputs(0)), g.activation(y, opt.FusedActivationFunction()), True)


def _logistic(g: _Graph, op: tflite.Operator) -> None:
    x = int(op.Inputs(0))
    four_d = len(g.shape(x)) == 4
    y = g.node("Sigmoid", [g.as_nchw(x) if four_d else g.as_plain(x)])
    g.bind(int(op.Outputs(0)), y, four_d)


_HANDLERS: dict[str, Callable[[_Graph, tflite.Operator], None]] = {
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


def convert(tflite_bytes: bytes, name: str = "model", dynamic_batch: bool = True) -> onnx.ModelProto:
    """Translate a float TFLite model (one subgraph, static shapes) into an ONNX model with the
    same input/output names, shapes and NHWC layout.

    dynamic_batch: the leading axis (1 in the TFLite file) becomes a free "batch" dimension, so
    all crops of a frame set run in one onnxruntime call.
    """
    try:
        model = tflite.Model.GetRootAsModel(tflite_bytes, 0)
        if model.SubgraphsLength() != 1:
            raise ModelError(f"{name}: expected one subgraph, found {model.SubgraphsLength()}")
        g = _Graph(model, tflite_bytes, dynamic_batch)
    except ModelError:
        raise
    except Exception as exc:  # a truncated/corrupt flatbuffer raises anything from struct to IndexError
        raise ModelError(f"{name}: not a readable TFLite flatbuffer ({exc})") from exc
    sub = g.sub
    graph_inputs = []
    for i in sub.InputsAsNumpy():
        i = int(i)
        g.bind(i, g.tname(i), False)
        graph_inputs.append(helper.make_tensor_value_info(g.tname(i), TensorProto.FLOAT, g.io_shape(i)))
    for k in range(sub.OperatorsLength()):
        op = sub.Operators(k)
        code = model.OperatorCodes(op.OpcodeIndex())
        opname = _OP_NAMES.get(max(code.BuiltinCode(), code.DeprecatedBuiltinCode()), "CUSTOM")
        handler = _HANDLERS.get(opname)
        if handler is None:
            raise ModelError(f"{name}: TFLite operator {opname} is not supported by vmocap's converter")
        handler(g, op)
    graph_outputs = []
    for i in sub.OutputsAsNumpy():
        i = int(i)
        g.node("Identity", [g.as_plain(i)], [g.tname(i)])
        graph_outputs.append(helper.make_tensor_value_info(g.tname(i), TensorProto.FLOAT, g.io_shape(i)))
    graph = helper.make_graph(g.nodes, name, graph_inputs, graph_outputs, g.inits)
    onnx_model = helper.make_model(graph, opset_imports=[helper.make_opsetid("", OPSET)], producer_name="vmocap.tflite2onnx")
    onnx_model.ir_version = 8
    onnx.checker.check_model(onnx_model)
    return onnx_model


def convert_file(src: Path, dst: Path) -> None:
    """Convert `src` (.tflite) into `dst` (.onnx), written atomically."""
    model = convert(Path(src).read_bytes(), Path(src).stem)
    tmp = Path(str(dst) + ".tmp")
    onnx.save(model, str(tmp))
    tmp.replace(dst)
