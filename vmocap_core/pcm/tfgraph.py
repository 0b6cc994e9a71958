"""A minimal reader of frozen TensorFlow GraphDef files (.pb) without TensorFlow.

Only what a frozen inference graph needs: nodes (name, op, inputs, attributes) and constant
tensors. The protobuf wire format is decoded directly (varint / 64-bit / length-delimited /
32-bit fields); field numbers follow tensorflow/core/framework/{graph,node_def,attr_value,
tensor,tensor_shape}.proto.
"""

from __future__ import annotations

import struct
from dataclasses import dataclass, field
from typing import Any, Iterator

import numpy as np

from ..errors import ModelError

# TensorFlow DataType enum -> numpy
TF_DTYPES = {1: np.float32, 2: np.float64, 3: np.int32, 4: np.uint8, 6: np.int8, 9: np.int64, 10: np.bool_, 19: np.float16}


def _varint(buf: bytes, pos: int) -> tuple[int, int]:
    result = shift = 0
    while True:
        b = buf[pos]
        pos += 1
        result |= (b & 0x7F) << shift
        if not b & 0x80:
            return result, pos
        shift += 7


def _fields(buf: bytes) -> Iterator[tuple[int, int, Any]]:
    """(field number, wire type, value) of one message; value is int or bytes."""
    pos, end = 0, len(buf)
    val: int | bytes  # by wire type
    while pos < end:
        key, pos = _varint(buf, pos)
        num, wt = key >> 3, key & 7
        if wt == 0:
            val, pos = _varint(buf, pos)
        elif wt == 1:
            val, pos = buf[pos : pos + 8], pos + 8
        elif wt == 2:
            n, pos = _varint(buf, pos)
            val, pos = buf[pos : pos + n], pos + n
        elif wt == 5:
            val, pos = buf[pos : pos + 4], pos + 4
        else:
            raise ModelError(f"unsupported protobuf wire type {wt}")
        if pos > end:
            raise ModelError("truncated protobuf message")
        yield num, wt, val


def _signed(v: int) -> int:
    return v - (1 << 64) if v >= 1 << 63 else v


def _shape(buf: bytes) -> list[int]:
    dims = []
    for num, _, val in _fields(buf):
        if num == 2:  # Dim
            size = 0
            for n2, _, v2 in _fields(val):
                if n2 == 1:
                    size = _signed(v2)
            dims.append(size)
    return dims


def _tensor(buf: bytes) -> np.ndarray:
    dtype_id, shape, content = 1, [], None
    floats: list[float] = []
    ints: list[int] = []
    for num, wt, val in _fields(buf):
        if num == 1:
            dtype_id = val
        elif num == 2:
            shape = _shape(val)
        elif num == 4:
            content = val
        elif num == 5:  # float_val, packed or not
            floats.extend(struct.unpack(f"<{len(val) // 4}f", val) if wt == 2 else struct.unpack("<f", val))
        elif num in (7, 10):  # int_val / int64_val
            if wt == 2:
                p = 0
                while p < len(val):
                    v, p = _varint(val, p)
                    ints.append(_signed(v))
            else:
                ints.append(_signed(val))
    dtype = TF_DTYPES.get(dtype_id)
    if dtype is None:
        raise ModelError(f"unsupported TensorFlow dtype {dtype_id}")
    n = int(np.prod(shape)) if shape else 1
    if content is not None:
        return np.frombuffer(content, dtype=dtype).reshape(shape).copy()
    vals = floats if floats else ints
    if not vals:
        return np.zeros(shape, dtype=dtype)
    arr: np.ndarray = np.array(vals, dtype=dtype)
    return (np.full(n, arr[-1], dtype=dtype) if arr.size < n else arr).reshape(shape)  # TF repeats the last value


@dataclass
class Node:
    name: str
    op: str
    inputs: list[str] = field(default_factory=list)
    attr: dict[str, Any] = field(default_factory=dict)  # int, float, bytes, list, shape or tensor by attr type


def _attr(buf: bytes) -> Any:
    for num, _wt, val in _fields(buf):
        if num == 2:
            return bytes(val)
        if num == 3:
            return _signed(val)
        if num == 4:
            return struct.unpack("<f", val)[0]
        if num in (5, 6):
            return int(val)
        if num == 7:
            return _shape(val)
        if num == 8:
            return _tensor(val)
        if num == 1:  # ListValue: ints / strings are what frozen graphs use (strides, ksize, padding lists)
            items: list[object] = []
            for n2, w2, v2 in _fields(val):
                if n2 == 3:
                    if w2 == 2:
                        p = 0
                        while p < len(v2):
                            x, p = _varint(v2, p)
                            items.append(_signed(x))
                    else:
                        items.append(_signed(v2))
                elif n2 == 2:
                    items.append(bytes(v2))
            return items
    return None


def read_graph(data: bytes) -> list[Node]:
    """Nodes of a frozen GraphDef in file order."""
    nodes = []
    try:
        for num, _, val in _fields(data):
            if num != 1:
                continue
            node = Node("", "")
            for n2, _, v2 in _fields(val):
                if n2 == 1:
                    node.name = bytes(v2).decode()
                elif n2 == 2:
                    node.op = bytes(v2).decode()
                elif n2 == 3:
                    node.inputs.append(bytes(v2).decode())
                elif n2 == 5:
                    key, value = "", None
                    for n3, _, v3 in _fields(v2):
                        if n3 == 1:
                            key = bytes(v3).decode()
                        elif n3 == 2:
                            value = _attr(v3)
                    node.attr[key] = value
            if not node.name or not node.op:
                raise ModelError("a node without name or operator")
            nodes.append(node)
    except (IndexError, UnicodeDecodeError, struct.error, ValueError) as exc:
        raise ModelError(f"not a readable TensorFlow GraphDef ({exc})") from exc
    if not nodes:
        raise ModelError("not a TensorFlow GraphDef: no nodes")
    return nodes
