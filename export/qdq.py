"""A quantised ONNX from elsewhere (QDQ format) as a float graph and the int8 quantisation it carries.

onnxruntime's ``quantize_static(..., quant_format=QuantFormat.QDQ)`` writes a model whose weights are int8
initializers behind ``DequantizeLinear`` (per output channel with ``per_channel=True``, symmetric), whose
biases are int32 in accumulator units, and whose activations pass through ``QuantizeLinear`` ->
``DequantizeLinear`` pairs (int8, one scale and zero point per tensor). :func:`split` turns it into

- the float graph the rest of the exporter reads: each constant ``DequantizeLinear`` becomes the float
  initializer it computes (``(q - zero) * scale``, float32, as onnxruntime computes it), each activation pair
  is removed; where a pair's range starts at 0 (zero point -128) the quantiser has fused away a ReLU, which
  is put back (``QuantizeLinear`` clamps below at the zero point, so ``Relu`` before it changes nothing);
- :class:`~embedrl.export.full_integer.Given`: each quantised activation's scale and zero point, by the
  float tensor's name, and each weight's per-output-channel scales, which ``--quantize int8-full`` then
  uses instead of calibrating (:func:`embedrl.export.full_integer.plan`): the C runs the model's own int8.

Anything else (a 16-bit or unsigned activation, a per-axis activation scale, a weight with a zero point, a
``QuantizeLinear`` not followed by its ``DequantizeLinear``) is refused in one line naming the node.
"""

from __future__ import annotations

import copy
from typing import Any

import numpy as np
import onnx
import onnxruntime as ort
from onnx import helper, numpy_helper

from embedrl.export.errors import UnsupportedOpError
from embedrl.export.full_integer import Activation, Given, IntegerSection, quantize_input
from embedrl.export.ir import Graph
from embedrl.export.onnx_import import to_ir

QUANTIZE, DEQUANTIZE = "QuantizeLinear", "DequantizeLinear"
INT8_MIN, INT8_MAX = -128, 127
"""int8's range; a zero point of -128 makes the range start at 0: the quantisation itself is a ReLU."""
RELU_SUFFIX = "_relu"
"""Appended to a quantised tensor's name for the ReLU put back before its pair."""


def is_qdq(model: onnx.ModelProto) -> bool:
    """Does the model hold QuantizeLinear or DequantizeLinear nodes?"""
    return any(n.op_type in (QUANTIZE, DEQUANTIZE) for n in model.graph.node)


def split(model: onnx.ModelProto) -> tuple[onnx.ModelProto, Given | None]:
    """The float model and the quantisation of a QDQ ``model``; ``(model, None)`` for any other model."""
    if not is_qdq(model):
        return model, None
    graph = model.graph
    constants = {init.name: numpy_helper.to_array(init) for init in graph.initializer}
    params = Given()
    rename: dict[str, str] = {}
    new_inits: list[onnx.TensorProto] = []
    kept: list[onnx.NodeProto] = []
    consumers = _consumers(graph)
    for node in graph.node:
        if node.op_type == DEQUANTIZE and node.input[0] in constants:
            value, scale = _dequantized(node, constants)
            new_inits.append(numpy_helper.from_array(value, node.output[0]))
            params.weight_scales[node.output[0]] = scale
        elif node.op_type == QUANTIZE:
            kept += _activation_pair(node, constants, consumers.get(node.output[0], []), params, rename)
        elif node.op_type == DEQUANTIZE:
            if node.output[0] not in rename:
                raise UnsupportedOpError(
                    f"DequantizeLinear node '{node.name}': its input '{node.input[0]}' is neither a constant "
                    "nor the output of a QuantizeLinear"
                )
        else:
            kept.append(node)
    out = copy.deepcopy(model)
    del out.graph.node[:]
    for node in kept:
        out.graph.node.append(node)  # a copy: the QDQ model stays as it was
        out.graph.node[-1].input[:] = [rename.get(i, i) for i in node.input]
    for value in out.graph.output:
        value.name = rename.get(value.name, value.name)
    used = {i for n in kept for i in n.input}
    del out.graph.initializer[:]
    out.graph.initializer.extend(i for i in [*graph.initializer, *new_inits] if i.name in used)
    return out, params


def _consumers(graph: onnx.GraphProto) -> dict[str, list[onnx.NodeProto]]:
    found: dict[str, list[onnx.NodeProto]] = {}
    for node in graph.node:
        for name in node.input:
            found.setdefault(name, []).append(node)
    return found


def _dequantized(node: onnx.NodeProto, constants: dict[str, np.ndarray]) -> tuple[np.ndarray, np.ndarray]:
    """A constant's float value and scales: ``(q - zero) * scale`` in float32 along the node's axis."""
    q = constants[node.input[0]]
    _check_scale(node, constants[node.input[1]])
    scale = np.asarray(constants[node.input[1]], np.float32)
    zero = np.asarray(constants[node.input[2]]) if len(node.input) > 2 and node.input[2] else np.zeros(1)
    if q.dtype not in (np.int8, np.int32) or np.any(zero != 0):
        raise UnsupportedOpError(
            f"DequantizeLinear node '{node.name}': constants must be int8 (weights) or int32 (biases) "
            f"with zero point 0, got {q.dtype} with zero point(s) {np.unique(zero).tolist()[:3]}"
        )
    axis = next((a.i for a in node.attribute if a.name == "axis"), 1)
    shape = [1] * q.ndim
    if scale.size > 1:
        shape[axis % q.ndim] = scale.size
    value = (q.astype(np.float32) * scale.reshape(shape)).astype(np.float32)
    return value, scale.reshape(-1)


def _check_scale(node: onnx.NodeProto, scale: np.ndarray) -> None:
    """A scale the integer C can use: float32, finite and positive (a zero or negative step has no integer
    meaning; a float16 scale is refused rather than silently widened)."""
    kind = "QuantizeLinear" if node.op_type == QUANTIZE else "DequantizeLinear"
    if scale.dtype != np.float32:
        raise UnsupportedOpError(
            f"{kind} node '{node.name}': its scale is {scale.dtype}; the int8 export takes float32 scales "
            "(quantise the model again with float32 scales)"
        )
    if not (np.all(np.isfinite(scale)) and np.all(scale > 0)):
        bad = scale[~(np.isfinite(scale) & (scale > 0))].reshape(-1)[:3].tolist()
        raise UnsupportedOpError(
            f"{kind} node '{node.name}': its scales must be finite and positive, got {bad} (a zero or "
            "negative step size quantises nothing)"
        )


def _activation_pair(
    node: onnx.NodeProto,
    constants: dict[str, np.ndarray],
    consumers: list[onnx.NodeProto],
    params: Given,
    rename: dict[str, str],
) -> list[onnx.NodeProto]:
    """Record a QuantizeLinear -> DequantizeLinear pair's quantisation; the ReLU it implies, if any."""
    if node.input[1] in constants:
        _check_scale(node, constants[node.input[1]])
    scale = np.asarray(constants.get(node.input[1], np.zeros(0)), np.float32)
    zero = np.asarray(constants.get(node.input[2], np.zeros(0)) if len(node.input) > 2 else np.zeros(0))
    if scale.size != 1 or zero.size != 1 or zero.dtype != np.int8:
        raise UnsupportedOpError(
            f"QuantizeLinear node '{node.name}': activations need one constant scale and an int8 zero point "
            f"(got {scale.size} scale(s), zero point {zero.dtype})"
        )
    if not consumers or any(
        c.op_type != DEQUANTIZE or list(c.input[1:]) != list(node.input[1:]) for c in consumers
    ):
        raise UnsupportedOpError(
            f"QuantizeLinear node '{node.name}': its output must go only to DequantizeLinear nodes with the "
            "same scale and zero point"
        )
    source, activation = node.input[0], Activation(float(scale.reshape(())), int(zero.reshape(())))
    added = []
    if activation.zero == INT8_MIN:
        relu = f"{source}{RELU_SUFFIX}"
        added.append(helper.make_node("Relu", [source], [relu], name=f"{node.name}{RELU_SUFFIX}"))
        source = relu
    params.activations[source] = activation
    for dequantize in consumers:
        rename[dequantize.output[0]] = source
    return added


def lowered(model: onnx.ModelProto) -> tuple[Graph, Given | None]:
    """The frozen IR of any model, a QDQ one through :func:`split`, and the quantisation it carries."""
    float_model, given = split(model)
    return to_ir(float_model), given


MAX_LAYER_STEPS = 1.0
"""How far each integer layer of the C may be from the QDQ model's, in steps of the model's quantisation of
the layer's output, given the same int8 input (the model's own): the C requantises with gemmlowp's fixed-point
multiplier and rounds half away from zero, the model (onnxruntime, and ONNX's reference, which agree)
multiplies in float32 and rounds half to even, so an output next to a rounding boundary may land one step
apart; the last layer keeps its int32 sums in the C where the model rounds them to its grid (half a step)."""


def compare(
    model: onnx.ModelProto, graph: Graph, section: IntegerSection, c_output: np.ndarray, samples: np.ndarray
) -> dict[str, Any]:
    """The C's integer section against onnxruntime running the QDQ ``model`` on ``samples``: layer by layer
    (each layer fed the model's own int8 input, its output compared in the model's steps) and end to end (the
    last layer's output ``c_output`` against the model's), leaving out outputs where the model saturates."""
    tensors = [section.input, *_layer_outputs(graph, section)]
    names = [_quantized_name(model, t) for t in tensors]
    probe = copy.deepcopy(model)
    for name in names:
        probe.graph.output.append(helper.make_tensor_value_info(name, onnx.TensorProto.INT8, None))
    session = ort.InferenceSession(probe.SerializeToString(), providers=["CPUExecutionProvider"])
    rows = np.asarray(samples, np.float32)
    name = session.get_inputs()[0].name
    if (
        session.get_inputs()[0].shape[0] == 1
    ):  # a file that fixes its batch at 1 (torch.onnx.export's default)
        runs = [session.run(names, {name: rows[i : i + 1]}) for i in range(len(rows))]
        ints = [np.concatenate([np.asarray(r[j], np.int64) for r in runs]) for j in range(len(names))]
    else:
        ints = [np.asarray(v, np.int64) for v in session.run(names, {name: rows})]
    activations = [section.quant, *(_given_activation(model, t) for t in tensors[1:])]
    layer_steps = [float(np.max(np.abs(quantize_input(samples, section.quant) - ints[0])))]
    for j, layer in enumerate(section.layers):
        mine, theirs = layer.reference(ints[j]), ints[j + 1]
        out = activations[j + 1]
        if j < len(section.layers) - 1:
            layer_steps.append(float(np.max(np.abs(mine - theirs))))
        else:
            layer_steps.append(_steps(np.asarray(mine, np.float64) / out.scale + out.zero, theirs))
    last = activations[-1]
    end_to_end = _steps(np.asarray(c_output, np.float64) / last.scale + last.zero, ints[-1])
    return {
        "reference": "onnxruntime running the QDQ model",
        "layers": [section.input, *(layer.name for layer in section.layers)],
        "max_layer_steps": layer_steps,
        "tolerance_steps": MAX_LAYER_STEPS,
        "end_to_end_max_output_steps": end_to_end,
        "output_step": last.scale,
    }


def _steps(mine: np.ndarray, theirs: np.ndarray) -> float:
    """Largest distance in steps where the model's int8 output does not saturate."""
    inside = (theirs > INT8_MIN) & (theirs < INT8_MAX)
    gaps = np.abs(mine - theirs)[inside]
    return float(gaps.max()) if gaps.size else 0.0


def _layer_outputs(graph: Graph, section: IntegerSection) -> list[str]:
    """Each integer layer's output tensor in the float graph (its ReLU's, where one follows)."""
    outputs: list[str] = []
    for node in graph.nodes:
        if node.name in section.nodes:
            if node.op == "Relu":
                outputs[-1] = node.outputs[0]
            else:
                outputs.append(node.outputs[0])
    return outputs


def _quantize_node(model: onnx.ModelProto, tensor: str) -> onnx.NodeProto:
    source = tensor[: -len(RELU_SUFFIX)] if tensor.endswith(RELU_SUFFIX) else tensor
    found = next(
        (n for n in model.graph.node if n.op_type == QUANTIZE and n.input[0] in (tensor, source)), None
    )
    if found is None:
        raise UnsupportedOpError(f"the quantised model does not quantise '{tensor}'")
    node: onnx.NodeProto = found
    return node


def _quantized_name(model: onnx.ModelProto, tensor: str) -> str:
    """The int8 tensor the model quantises ``tensor`` (a float graph tensor) into."""
    return str(_quantize_node(model, tensor).output[0])


def _given_activation(model: onnx.ModelProto, tensor: str) -> Activation:
    node = _quantize_node(model, tensor)
    constants = {i.name: numpy_helper.to_array(i) for i in model.graph.initializer}
    return Activation(float(constants[node.input[1]].reshape(())), int(constants[node.input[2]].reshape(())))
