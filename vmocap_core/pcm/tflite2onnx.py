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
The operators' translations are in tflite_ops.py, the tensors and their layout in tflite_graph.py.
"""

from __future__ import annotations

from pathlib import Path

import onnx
import tflite
from onnx import TensorProto, helper

from ..errors import ModelError
from .tflite_graph import Graph
from .tflite_ops import HANDLERS

OPSET = 18
CONVERTER_VERSION = "2"  # bump when the translation changes (invalidates cached ONNX files)

_OP_NAMES = {v: k for k, v in vars(tflite.BuiltinOperator).items() if not k.startswith("_")}


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
        g = Graph(model, tflite_bytes, dynamic_batch)
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
        handler = HANDLERS.get(opname)
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
