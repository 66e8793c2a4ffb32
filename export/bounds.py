"""Where a policy's actions can go: interval bounds through the graph, and a clamp when they can leave
the action space.

Each op gives its own interval rule (:meth:`Emitter.bounds <embedrl.export.ops.base.Emitter.bounds>`): a
monotone op from its reference at the interval's two ends, a matrix product row by row, any other op
unbounded. An op with two runtime operands gives up (unbounded), which is the safe answer. The bounds start
from the observation space's.

A policy whose bounds leave the action space (an ONNX from elsewhere without tanh or clip at its end,
for example) gets ``Max(low)`` and ``Min(high)`` appended to its ONNX, so the exported graph, its C and
every verification see clamped actions; the report says so.
"""

from __future__ import annotations

import numpy as np
import onnx
from onnx import helper, numpy_helper

from embedrl.export.ir import Graph
from embedrl.export.ops import EMITTERS
from embedrl.export.ops.base import Interval

SLACK = 1e-6
"""Relative slack when comparing bounds with the action space (float32 rounding of affine rescaling)."""
CLAMP_LOW, CLAMP_HIGH = "embedrl_action_low", "embedrl_action_high"


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
        size = int(np.prod(graph.shapes[node.outputs[0]]))
        emitter = EMITTERS[node.op]
        if runtime and not emitter.bounded_by_itself:  # two runtime operands: no interval rule here
            out = (np.full(size, -np.inf), np.full(size, np.inf))
        else:
            out = emitter.bounds(node, values[node.inputs[0]], graph.constants, size)
        lo, hi = out
        bad = np.isnan(lo) | np.isnan(hi)
        values[node.outputs[0]] = (np.where(bad, -np.inf, lo), np.where(bad, np.inf, hi))
        later = node.outputs[1:]
        extras = emitter.later_bounds(
            node, values[node.outputs[0]], [graph.size(o) if o else 0 for o in later]
        )
        values.update((o, b) for o, b in zip(later, extras, strict=True) if o)
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
