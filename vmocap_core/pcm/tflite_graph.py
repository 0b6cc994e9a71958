"""TFLite tensors during the conversion to ONNX (tflite2onnx.py): values, names and layout.

`Graph` holds the ONNX nodes and initializers written so far and, per TFLite tensor, either its
constant value (constant subgraphs are folded at conversion time) or its ONNX name and whether
that ONNX value is the NCHW transpose of the NHWC tensor; `as_nchw` / `as_plain` add a Transpose
only where a reader needs the other order. `densify` expands TFLite's sparse weight tensors.
"""

from __future__ import annotations

from typing import Any

import numpy as np
import onnx
import tflite
from onnx import helper, numpy_helper

from ..errors import ModelError

_NP_TYPES = {
    tflite.TensorType.FLOAT32: np.float32,
    tflite.TensorType.FLOAT16: np.float16,
    tflite.TensorType.INT32: np.int32,
    tflite.TensorType.INT64: np.int64,
    tflite.TensorType.UINT8: np.uint8,
    tflite.TensorType.INT8: np.int8,
}
NHWC_TO_NCHW = (0, 3, 1, 2)
NCHW_TO_NHWC = (0, 2, 3, 1)


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


class Graph:
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
            return self.const(np.transpose(self.consts[i], NHWC_TO_NCHW), self.tname(i))
        if self.nchw[i]:
            return self.names[i]
        key = (i, "nchw")
        if key not in self._cache:
            self._cache[key] = self.node("Transpose", [self.names[i]], perm=list(NHWC_TO_NCHW))
        return self._cache[key]

    def as_plain(self, i: int) -> str:
        """ONNX name of tensor i in TFLite's own (NHWC) order."""
        if i in self.consts:
            return self.const(self.consts[i], self.tname(i))
        if not self.nchw[i]:
            return self.names[i]
        key = (i, "plain")
        if key not in self._cache:
            self._cache[key] = self.node("Transpose", [self.names[i]], perm=list(NCHW_TO_NHWC))
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
