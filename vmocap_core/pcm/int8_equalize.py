"""Cross-layer equalization (Nagel et al. 2019) of the residual streams of a prepared graph.

The linear tensors of a residual stream (Conv outputs without activation joined by Adds, read
only by Convs) take a scale s_c per channel: channel c of every producer is multiplied by s_c,
input channel c of every reader by 1 / s_c, which leaves the float function as it is. The
scales widen the narrow channels to the per-tensor uint8 grid the widest channel sets.
quantize.calibrate() computes them from calibration ranges (`equalization_scales`), the
calibration file stores them and quantize.build() applies them (`equalize`).
"""

from __future__ import annotations

import numpy as np
import onnx
from onnx import numpy_helper

from ..errors import ModelError


def _consumers(g: onnx.GraphProto) -> dict[str, list[onnx.NodeProto]]:
    out: dict[str, list[onnx.NodeProto]] = {}
    for n in g.node:
        for i in n.input:
            out.setdefault(i, []).append(n)
    return out


def _group(n: onnx.NodeProto) -> int:
    return next((a.i for a in n.attribute if a.name == "group"), 1)


def equalization_groups(model: onnx.ModelProto) -> list[dict]:
    """Channel groups whose channels can be rescaled without changing the network's function:
    the linear tensors of a residual stream (Conv outputs without activation joined by Adds) whose
    every reader is a Conv. Scaling channel c of every producer (weights and bias) by s_c and the
    input channel c of every reader by 1 / s_c is exact (no activation in between). Graph order."""
    g = model.graph
    inits = {i.name for i in g.initializer}
    producer = {o: n for n in g.node for o in n.output}
    consumers = _consumers(g)
    parent: dict[str, str] = {}

    def find(t: str) -> str:
        while parent.setdefault(t, t) != t:
            t = parent[t]
        return t

    for n in g.node:
        if n.op_type == "Add" and not any(i in inits for i in n.input):
            for i in n.input:
                parent[find(i)] = find(n.output[0])
    members: dict[str, list[str]] = {}
    for n in g.node:
        if n.op_type in ("Conv", "Add"):
            members.setdefault(find(n.output[0]), []).append(n.output[0])
    groups = []
    for tensors in members.values():
        root = find(tensors[0])
        producers, readers, ok = [], [], True
        for t in tensors:
            p = producer[t]
            if p.op_type == "Conv":
                producers.append(p.name)
            elif not (p.op_type == "Add" and all(find(i) == root for i in p.input)):
                ok = False
            for c in consumers.get(t, []):
                if c.op_type == "Conv" and c.input[0] == t:
                    readers.append(c.name)
                elif not (c.op_type == "Add" and find(c.output[0]) == root):
                    ok = False
        if ok and producers and readers:
            groups.append({"tensors": tensors, "producers": producers, "readers": list(dict.fromkeys(readers))})
    return groups


def equalization_scales(groups: list[dict], low: dict[str, np.ndarray], high: dict[str, np.ndarray],
                        max_scale: float = 1000.0) -> dict[str, list[float]]:
    """Per group (keyed by its first tensor), the largest channel scales that keep every tensor of
    the group inside its calibrated range: narrow channels are widened to use the per-tensor uint8
    grid that the widest channel sets (cross-layer equalization, Nagel et al. 2019)."""
    out = {}
    for gr in groups:
        s = np.full(np.asarray(high[gr["tensors"][0]]).size, np.inf)
        for t in gr["tensors"]:
            h, lo = np.asarray(high[t], np.float64), np.asarray(low[t], np.float64)
            with np.errstate(divide="ignore", invalid="ignore"):
                s = np.minimum(s, np.where(h > 1e-9, h.max() / h, np.inf))
                s = np.minimum(s, np.where(lo < -1e-9, lo.min() / lo, np.inf))
        s = np.where(np.isfinite(s), np.clip(s, 1.0, max_scale), 1.0)
        out[gr["tensors"][0]] = [float(np.float32(v)) for v in s]
    return out


def equalize(model: onnx.ModelProto, scales: dict[str, list[float]]) -> None:
    """Apply `equalization_scales` in place (the groups are found again in the graph)."""
    g = model.graph
    inits = {i.name: i for i in g.initializer}
    nodes = {n.name: n for n in g.node}
    factor_out: dict[str, np.ndarray] = {}
    factor_in: dict[str, np.ndarray] = {}
    groups = {gr["tensors"][0]: gr for gr in equalization_groups(model)}
    for key, s in scales.items():
        if key not in groups:
            raise ModelError(f"equalization group {key} is not in the prepared graph")
        sc = np.asarray(s, np.float64)
        for p in groups[key]["producers"]:
            factor_out[p] = factor_out.get(p, 1.0) * sc
        for r in groups[key]["readers"]:
            factor_in[r] = factor_in.get(r, 1.0) / sc
    for name in sorted(set(factor_out) | set(factor_in)):
        n = nodes[name]
        W = numpy_helper.to_array(inits[n.input[1]]).astype(np.float64)
        if name in factor_in:
            f = factor_in[name]
            W = W * (f.reshape(1, -1, 1, 1) if _group(n) == 1 else f.reshape(-1, 1, 1, 1))
        if name in factor_out:
            W = W * factor_out[name].reshape(-1, 1, 1, 1)
            if len(n.input) > 2 and n.input[2]:
                b = numpy_helper.to_array(inits[n.input[2]]).astype(np.float64) * factor_out[name]
                inits[n.input[2]].CopyFrom(numpy_helper.from_array(b.astype(np.float32), n.input[2]))
        inits[n.input[1]].CopyFrom(numpy_helper.from_array(W.astype(np.float32), n.input[1]))
