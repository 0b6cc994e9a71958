"""The frozen-TensorFlow-graph translator against a numpy reference of TensorFlow's semantics
(NHWC, SAME padding with the extra pixel at the end, depthwise channel order), on a small graph
written here in protobuf wire format, with image sizes that make SAME padding asymmetric."""

from __future__ import annotations

import numpy as np
import onnxruntime as ort
import pytest

from vmocap_core.errors import ModelError
from vmocap_core.pcm.tfgraph import read_graph
from vmocap_core.pcm.tfgraph2onnx import convert


# -- a minimal protobuf writer ------------------------------------------------------------
def _varint(n: int) -> bytes:
    n &= (1 << 64) - 1
    out = bytearray()
    while True:
        b = n & 0x7F
        n >>= 7
        out.append(b | (0x80 if n else 0))
        if not n:
            return bytes(out)


def _ld(field: int, data: bytes) -> bytes:
    return _varint(field << 3 | 2) + _varint(len(data)) + data


def _vi(field: int, n: int) -> bytes:
    return _varint(field << 3) + _varint(n)


def _tensor(a: np.ndarray) -> bytes:
    dtype = {np.dtype(np.float32): 1, np.dtype(np.int32): 3}[a.dtype]
    shape = b"".join(_ld(2, _vi(1, d)) for d in a.shape)
    return _vi(1, dtype) + _ld(2, shape) + _ld(4, a.tobytes())


def _attr(value: object) -> bytes:
    if isinstance(value, np.ndarray):
        return _ld(8, _tensor(value))
    if isinstance(value, bytes):
        return _ld(2, value)
    if isinstance(value, list):
        return _ld(1, b"".join(_vi(3, v) for v in value))
    return _vi(6, int(value))  # a dtype


def _node(name: str, op: str, inputs: list[str], **attrs: object) -> bytes:
    body = _ld(1, name.encode()) + _ld(2, op.encode()) + b"".join(_ld(3, i.encode()) for i in inputs)
    for k, v in attrs.items():
        body += _ld(5, _ld(1, k.encode()) + _ld(2, _attr(v)))
    return _ld(1, body)


# -- numpy reference of TensorFlow's ops ---------------------------------------------------
def _same(n: int, k: int, s: int) -> tuple[int, int, int]:
    out = -(-n // s)
    total = max((out - 1) * s + k - n, 0)
    return out, total // 2, total - total // 2


def _patches(x: np.ndarray, k: int, s: int, same: bool, fill: float) -> np.ndarray:
    """(H', W', k, k, C) windows of x (H, W, C)."""
    H, W, C = x.shape
    if same:
        oh, t, b = _same(H, k, s)
        ow, l, r = _same(W, k, s)
        x = np.pad(x, ((t, b), (l, r), (0, 0)), constant_values=fill)
    else:
        oh, ow = (H - k) // s + 1, (W - k) // s + 1
    return np.stack([[x[i * s : i * s + k, j * s : j * s + k] for j in range(ow)] for i in range(oh)])


def _conv(x: np.ndarray, w: np.ndarray, s: int, same: bool) -> np.ndarray:  # w: HWIO
    return np.einsum("ijabc,abcd->ijd", _patches(x, w.shape[0], s, same, 0.0), w)


def _depthwise(x: np.ndarray, w: np.ndarray, s: int) -> np.ndarray:  # w: (k, k, C, M)
    y = np.einsum("ijabc,abcm->ijcm", _patches(x, w.shape[0], s, True, 0.0), w)
    return y.reshape(y.shape[0], y.shape[1], -1)  # channel c * M + m


def _maxpool(x: np.ndarray, k: int, s: int) -> np.ndarray:
    return _patches(x, k, s, True, -np.inf).max(axis=(2, 3))


def test_tf_graph_translation_matches_tensorflow_semantics() -> None:
    rng = np.random.default_rng(3)
    f32 = lambda *shape: rng.standard_normal(shape).astype(np.float32)  # noqa: E731
    w0, b0, wd, w1 = f32(3, 3, 3, 4), f32(4), f32(3, 3, 4, 2), f32(1, 1, 8, 5)
    nhwc, same, valid = b"NHWC", b"SAME", b"VALID"
    graph = b"".join([
        _node("image", "Placeholder", [], dtype=1),
        _node("w0", "Const", [], value=w0), _node("b0", "Const", [], value=b0),
        _node("wd", "Const", [], value=wd), _node("w1", "Const", [], value=w1),
        _node("axis", "Const", [], value=np.array(3, np.int32)),
        _node("conv0", "Conv2D", ["image", "w0"], strides=[1, 2, 2, 1], padding=same, data_format=nhwc),
        _node("bias0", "BiasAdd", ["conv0", "b0"]),
        _node("relu0", "Relu", ["bias0"]),
        _node("dw", "DepthwiseConv2dNative", ["relu0", "wd"], strides=[1, 1, 1, 1], padding=same, data_format=nhwc),
        _node("pool", "MaxPool", ["dw"], ksize=[1, 2, 2, 1], strides=[1, 2, 2, 1], padding=same, data_format=nhwc),
        _node("conv1", "Conv2D", ["dw", "w1"], strides=[1, 2, 2, 1], padding=valid, data_format=nhwc),
        _node("out", "ConcatV2", ["pool", "conv1", "axis"]),
    ])
    W, H = 12, 14  # even: stride-2 SAME pads 0 before, 1 after (asymmetric)
    model = convert(read_graph(graph), "out", (W, H), "tiny")
    x = f32(2, H, W, 3) * 50
    sess = ort.InferenceSession(model.SerializeToString(), providers=["CPUExecutionProvider"])
    got = sess.run(None, {"image": x})[0]
    for n in range(2):
        h = np.maximum(_conv(x[n], w0, 2, True) + b0, 0)
        d = _depthwise(h, wd, 1)
        ref = np.concatenate([_maxpool(d, 2, 2), _conv(d, w1, 2, False)], axis=2)
        assert got[n].shape == ref.shape == (4, 3, 13)
        np.testing.assert_allclose(got[n], ref, rtol=1e-4, atol=1e-3)
    # an operator the translator does not know is named, not mistranslated
    bad = graph + _node("soft", "Softmax", ["out"])
    with pytest.raises(ModelError, match="Softmax"):
        convert(read_graph(bad), "soft", (W, H), "tiny")
