"""GPTQ rounding (Frantar et al. 2022) of convolution weights to the int8 grid.

Instead of rounding every weight to nearest, the columns of a weight matrix are rounded in turn
and the error of each is pushed onto the columns not yet rounded and onto the bias, using the
second moments of the layer's input on the calibration crops (`conv_patches`: 1 x 1 and
depthwise convolutions). quantize.calibrate() runs it and stores the result in the calibration
file, so quantize.build() needs neither data nor linear algebra.
"""

from __future__ import annotations

import numpy as np
import onnx

from ..errors import ModelError


def conv_patches(x: np.ndarray, n: onnx.NodeProto, W: np.ndarray) -> np.ndarray:
    """Conv input patches: (positions, C) for a 1 x 1 conv, (C, positions, k*k) for a depthwise one."""
    attrs = {a.name: onnx.helper.get_attribute_value(a) for a in n.attribute}
    st = list(attrs.get("strides", [1, 1]))
    pads = list(attrs.get("pads", [0, 0, 0, 0]))
    O, I, kh, kw = W.shape
    xp = np.pad(x, ((0, 0), (0, 0), (pads[0], pads[2]), (pads[1], pads[3])))
    ho, wo = (xp.shape[2] - kh) // st[0] + 1, (xp.shape[3] - kw) // st[1] + 1
    cols = [xp[:, :, dy : dy + st[0] * (ho - 1) + 1 : st[0], dx : dx + st[1] * (wo - 1) + 1 : st[1]]
            for dy in range(kh) for dx in range(kw)]
    P = np.stack(cols, 2)  # N, C, k*k, ho, wo
    if attrs.get("group", 1) == 1:
        if kh * kw != 1:
            raise ModelError(f"{n.name}: GPTQ handles 1 x 1 and depthwise convolutions only")
        return P[:, :, 0].transpose(0, 2, 3, 1).reshape(-1, P.shape[1])
    return P.transpose(1, 0, 3, 4, 2).reshape(P.shape[1], -1, kh * kw)


def gptq_rows(W: np.ndarray, b: np.ndarray, H: np.ndarray, scale: np.ndarray, damp: float = 0.01,
              qmax: int = 127) -> tuple[np.ndarray, np.ndarray]:
    """GPTQ (Frantar et al. 2022) of rows W (O, d) sharing H = E[[x, 1][x, 1]^T] (d + 1 square):
    columns are rounded one by one to the grid `scale` (per row, integers within +-qmax) and the rounding error is
    pushed onto the columns not yet rounded and onto the bias (the last, never rounded, column),
    minimizing the output error on the calibration inputs. Returns (int weights, new bias)."""
    O, d = W.shape
    Hd = H.astype(np.float64).copy()
    Hd[np.arange(d + 1), np.arange(d + 1)] += damp * np.mean(np.diag(Hd)[:d]) + 1e-9
    Hinv = np.linalg.inv(Hd)
    V = np.concatenate([W.astype(np.float64), b.astype(np.float64)[:, None]], 1)
    s = scale.astype(np.float64)
    q = np.zeros((O, d), np.int64)
    alive = np.ones(d + 1, bool)
    for j in range(d):
        q[:, j] = np.clip(np.round(V[:, j] / s), -qmax, qmax)
        err = (V[:, j] - q[:, j] * s) / Hinv[j, j]
        alive[j] = False
        V[:, alive] -= np.outer(err, Hinv[j, alive])
        Hinv = Hinv - np.outer(Hinv[:, j], Hinv[j, :]) / Hinv[j, j]
    return q, V[:, d]


def weight_scale(W: np.ndarray, qmax: int = 127) -> np.ndarray:
    """The per-output-channel symmetric scale quantize_static gives these weights on the grid
    -qmax..qmax (127: int8; 64: its reduce_range grid)."""
    a = np.abs(W.astype(np.float32).reshape(W.shape[0], -1)).max(1)
    s = (a * np.float32(2.0) / np.float32(2 * qmax)).astype(np.float32)
    return np.where(s == 0, np.float32(1.0), s)
