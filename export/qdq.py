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
from embedrl.export.full_integer import Activation, Given
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


def _activation_pair(
    node: onnx.NodeProto,
    constants: dict[str, np.ndarray],
    consumers: list[onnx.NodeProto],
    params: Given,
    rename: dict[str, str],
) -> list[onnx.NodeProto]:
    """Record a QuantizeLinear -> DequantizeLinear pair's quantisation; the ReLU it implies, if any."""
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


MAX_OUTPUT_STEPS = 2.0
"""How far the C's last-layer output may be from the QDQ model's, in steps of its output quantisation, where
that quantisation does not saturate. The C requantises hidden layers with gemmlowp's fixed-point multiplier,
the model (onnxruntime, and ONNX's reference, which agree) in float32: a hidden value one step apart moves the
output by up to ~1.7 steps on the study's actor; and the C keeps the last layer's int32 sums, the model rounds
them to its int8 grid (half a step)."""


def compare(
    model: onnx.ModelProto, section_output: str, given: Given, c_output: np.ndarray, samples: np.ndarray
) -> dict[str, Any]:
    """The C's last integer layer (``c_output``, float, before the output non-linearity) against onnxruntime
    running the QDQ ``model`` on ``samples``, in steps of the model's quantisation of that tensor."""
    pair = next(
        (
            (q, d)
            for q in model.graph.node
            if q.op_type == QUANTIZE and section_output in (q.input[0], f"{q.input[0]}{RELU_SUFFIX}")
            for d in model.graph.node
            if d.op_type == DEQUANTIZE and d.input[0] == q.output[0]
        ),
        None,
    )
    if pair is None:
        raise UnsupportedOpError(
            f"the quantised model does not quantise the last layer's output '{section_output}'"
        )
    probe = copy.deepcopy(model)
    probe.graph.output.append(helper.make_tensor_value_info(pair[1].output[0], onnx.TensorProto.FLOAT, None))
    session = ort.InferenceSession(probe.SerializeToString(), providers=["CPUExecutionProvider"])
    inputs = {probe.graph.input[0].name: np.asarray(samples, np.float32)}
    model_output = np.asarray(session.run([pair[1].output[0]], inputs)[0], np.float64).reshape(c_output.shape)
    activation = given.activations[section_output]
    low, high = (
        activation.scale * (INT8_MIN - activation.zero),
        activation.scale * (INT8_MAX - activation.zero),
    )
    margin = activation.scale / 2  # the model's values are on its grid: the end points, or a step inside
    saturated = (model_output <= low + margin) | (model_output >= high - margin)
    steps = np.abs(np.asarray(c_output, np.float64) - model_output)[~saturated] / activation.scale
    return {
        "reference": "onnxruntime running the QDQ model",
        "output_tensor": section_output,
        "output_step": activation.scale,
        "max_output_steps": float(steps.max()) if steps.size else 0.0,
        "p99_output_steps": float(np.percentile(steps, 99)) if steps.size else 0.0,
        "saturated_outputs": int(saturated.sum()),
        "tolerance_steps": MAX_OUTPUT_STEPS,
    }
