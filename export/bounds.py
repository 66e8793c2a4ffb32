"""Where a policy's actions can go: interval bounds through the graph, and a clamp when they can leave
the action space.

Every element-wise op here is monotone in its runtime input for a fixed constant operand (increasing or,
for a negative factor, decreasing), so its output interval is spanned by its reference at the interval's
two ends. Matrix products with constant weights are bounded row by row. An op with two runtime operands
gives up (unbounded), which is the safe answer. The bounds start from the observation space's.

A policy whose bounds leave the action space (an ONNX from elsewhere without tanh or clip at its end,
for example) gets ``Max(low)`` and ``Min(high)`` appended to its ONNX, so the exported graph, its C and
every verification see clamped actions; the report says so.
"""

from __future__ import annotations

import numpy as np
import onnx
from onnx import helper, numpy_helper

from embedrl.export.ir import Graph, Node
from embedrl.export.ops import EMITTERS

Interval = tuple[np.ndarray, np.ndarray]
SLACK = 1e-6
"""Relative slack when comparing bounds with the action space (float32 rounding of affine rescaling)."""
CLAMP_LOW, CLAMP_HIGH = "embedrl_action_low", "embedrl_action_high"


def _matmul(node: Node, x: Interval, graph: Graph) -> Interval:
    w = graph.constants[node.inputs[1]].astype(np.float64)
    if node.op == "Gemm" and int(node.attr("transB", 0)):
        w = w.T
    lo, hi = (v.reshape(-1, 1) for v in x)
    with np.errstate(invalid="ignore"):
        a, b = np.where(w == 0, 0.0, lo * w), np.where(w == 0, 0.0, hi * w)
    out_lo, out_hi = np.minimum(a, b).sum(axis=0), np.maximum(a, b).sum(axis=0)
    if node.op == "Gemm":
        alpha, beta = float(node.attr("alpha", 1.0)), float(node.attr("beta", 1.0))
        out_lo, out_hi = (
            np.minimum(alpha * out_lo, alpha * out_hi),
            np.maximum(alpha * out_lo, alpha * out_hi),
        )
        if len(node.inputs) > 2 and node.inputs[2]:
            c = beta * graph.constants[node.inputs[2]].astype(np.float64).reshape(-1)
            out_lo, out_hi = out_lo + c, out_hi + c
    return out_lo, out_hi


def action_bounds(graph: Graph, obs_low: np.ndarray, obs_high: np.ndarray) -> Interval:
    """Lower and upper bounds of every action the graph can produce for observations in the box."""
    values: dict[str, Interval] = {
        graph.input: (
            np.asarray(obs_low, np.float64).reshape(-1),
            np.asarray(obs_high, np.float64).reshape(-1),
        )
    }
    for node in graph.nodes:
        runtime = [i for i in node.inputs[1:] if i and i not in graph.constants]
        x = values[node.inputs[0]]
        if node.op in ("Gemm", "MatMul"):
            out = _matmul(node, x, graph)
        elif runtime:
            size = graph.shapes[node.outputs[0]]
            n = int(np.prod(size))
            out = (np.full(n, -np.inf), np.full(n, np.inf))
        else:
            emitter = EMITTERS[node.op]
            ends = [
                emitter.reference(node, [end.reshape(1, -1)] + [
                    graph.constants[i].astype(np.float64).reshape(-1) for i in node.inputs[1:] if i
                ], graph.constants, "float64").reshape(-1)
                for end in x
            ]  # fmt: skip
            out = (np.minimum(*ends), np.maximum(*ends))
        lo, hi = out
        bad = np.isnan(lo) | np.isnan(hi)
        values[node.outputs[0]] = (np.where(bad, -np.inf, lo), np.where(bad, np.inf, hi))
    return values[graph.output]


def within(bounds: Interval, low: np.ndarray, high: np.ndarray) -> bool:
    lo, hi = bounds
    span = np.maximum(np.abs(low), np.abs(high)) * SLACK
    return bool(np.all(lo >= low - span) and np.all(hi <= high + span))


def append_clamp(model: onnx.ModelProto, low: np.ndarray, high: np.ndarray) -> onnx.ModelProto:
    """A copy of ``model`` whose output is ``Min(Max(output, low), high)`` (same output name)."""
    clamped = onnx.ModelProto()
    clamped.CopyFrom(model)
    g = clamped.graph
    out = g.output[0].name
    raw, floor = f"{out}_unclamped", f"{out}_floored"
    for node in g.node:
        node.output[:] = [raw if o == out else o for o in node.output]
    g.initializer.extend(
        [
            numpy_helper.from_array(np.asarray(low, np.float32).reshape(-1), CLAMP_LOW),
            numpy_helper.from_array(np.asarray(high, np.float32).reshape(-1), CLAMP_HIGH),
        ]
    )
    g.node.extend(
        [
            helper.make_node("Max", [raw, CLAMP_LOW], [floor], name="clamp_to_action_low"),
            helper.make_node("Min", [floor, CLAMP_HIGH], [out], name="clamp_to_action_high"),
        ]
    )
    return clamped
