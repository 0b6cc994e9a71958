"""The float landmark graph made ready for int8 quantization, computing the same function.

`prepare()` names the nodes (quantize_static and the calibration file refer to nodes by name),
folds each explicit Pad into the Conv that reads it and replaces each bilinear Resize by two
MatMuls with the same interpolation weights (`linear_resize_matrix`, which budget.py also uses
to resize those matrices). quantize.py has the method as a whole.
"""

from __future__ import annotations

import numpy as np
import onnx
from onnx import numpy_helper, shape_inference

from ..errors import ModelError


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
    drop, resize_as_matmul = [], []
    for k, n in enumerate(g.node):
        n.name = n.name or f"{n.op_type}_{k}"
        if n.op_type == "Resize" and len(n.input) == 4 and n.input[3] in inits:
            sizes = numpy_helper.to_array(inits[n.input[3]])
            shape = shapes.get(n.input[0], [])
            axes = [list(a.ints) for a in n.attribute if a.name == "axes"]
            if len(shape) != 4 or not all(shape[2:]) or axes not in ([[2, 3]], []) or sizes.size != 2:
                raise ModelError(f"{n.name}: unexpected Resize (sizes {sizes}, input shape {shape}, axes {axes})")
            attrs = {a.name: onnx.helper.get_attribute_value(a) for a in n.attribute}
            if attrs.get("mode") != b"linear" or attrs.get("coordinate_transformation_mode") != b"half_pixel":
                raise ModelError(f"{n.name}: only bilinear half_pixel Resize is supported ({attrs})")
            resize_as_matmul.append((n, int(shape[2]), int(shape[3]), int(sizes[0]), int(sizes[1])))
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
    for n, h, w, out_h, out_w in resize_as_matmul:
        _resize_to_matmul(g, n, h, w, out_h, out_w)
    used = {i for n in g.node for i in n.input}
    for t in [t for t in g.initializer if t.name not in used]:  # the replaced sizes and pads
        g.initializer.remove(t)
    del g.value_info[:]
    return m


def linear_resize_matrix(n_in: int, n_out: int) -> np.ndarray:
    """(n_out, n_in) weights of ONNX Resize mode=linear, coordinate_transformation_mode=half_pixel
    along one axis: output i samples x = (i + 0.5) n_in / n_out - 0.5, clamped to the edge pixels."""
    A = np.zeros((n_out, n_in), np.float64)
    for i in range(n_out):
        x = min(max((i + 0.5) * n_in / n_out - 0.5, 0.0), n_in - 1.0)
        i0 = int(np.floor(x))
        i1, f = min(i0 + 1, n_in - 1), x - i0
        A[i, i0] += 1.0 - f
        A[i, i1] += f
    return A.astype(np.float32)


def _resize_to_matmul(g: onnx.GraphProto, n: onnx.NodeProto, h: int, w: int, out_h: int, out_w: int) -> None:
    """Replace a bilinear Resize of an (N, C, h, w) tensor by x @ A_w^T then A_h @ (...): the same
    weights (each output is a 2 x 2 weighted sum, the other products are exact zeros), run by
    onnxruntime's GEMM instead of its NCHW Resize kernel (32 x 32 -> 64 x 64 x 48: 0.8-0.9 ms of a
    ~15 ms crop, the GEMMs ~0.2 ms)."""
    a_w, a_h = n.name + "_cols", n.name + "_rows"
    g.initializer.extend([numpy_helper.from_array(np.ascontiguousarray(linear_resize_matrix(w, out_w).T), a_w),
                          numpy_helper.from_array(linear_resize_matrix(h, out_h), a_h)])
    k = list(g.node).index(n)
    first = onnx.helper.make_node("MatMul", [n.input[0], a_w], [n.output[0] + "_cols"], name=n.name + "_cols")
    second = onnx.helper.make_node("MatMul", [a_h, n.output[0] + "_cols"], [n.output[0]], name=n.name)
    g.node.remove(n)
    g.node.insert(k, second)
    g.node.insert(k, first)
