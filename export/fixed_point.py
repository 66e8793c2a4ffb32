"""``--quantize q15``: 16-bit fixed point for FPU-less cores, and its exact Python model.

The chain of Gemm layers (with ReLU between them) runs in integers: activations are int16 with a
power-of-two scale per tensor (``frac`` fractional bits, calibrated on the verification
observations with headroom), weights are int16 with a power-of-two scale per output channel,
products accumulate in int64 with the bias, and each layer requantises with a rounding right
shift and saturates to int16. ReLU is fused. Only the edges are float: the observation (after any
normalisation) is scaled and rounded into int16 once, and the last layer's accumulator is
converted to float once, before the output non-linearity (deterministic tanh, see export.quantize)
and the action post-processing. On a Cortex-M3 that leaves a handful of software-float operations
per step instead of one per multiply-add.

Integer sums are exact in any order, so the C computes each output as a dot product (weights stored
output-major) and the int64 numpy model here reproduces it bit for bit; the float edges use the same
IEEE operations in the same order as the C. Signed right shifts are arithmetic with gcc (documented
implementation-defined behaviour), as in numpy.
"""

from __future__ import annotations

import math
from dataclasses import dataclass

import numpy as np

from embedrl.export import interpret
from embedrl.export.contract.literals import c_float
from embedrl.export.errors import UnsupportedOpError
from embedrl.export.ir import Graph, Node
from embedrl.export.ops import EMITTERS
from embedrl.export.ops.base import EmitContext
from embedrl.export.ops.linear import Q15_MAX as Q_MAX
from embedrl.export.ops.linear import Q15Layer

F = np.float32
HEADROOM = 1.5
"""Calibrated activation ranges are widened by this factor before choosing the scale."""
MAX_FRAC = 24


@dataclass(frozen=True)
class FixedSection:
    """The integer part of the graph: from ``input`` (float, quantised on entry) to ``output`` (float)."""

    input: str
    output: str
    in_frac: int
    layers: tuple[Q15Layer, ...]
    nodes: frozenset[str]
    """Names of the IR nodes the section replaces."""
    first_node: str

    def run(self, x: np.ndarray) -> np.ndarray:
        """:func:`run` of this section."""
        return run(self, x)

    def buffer_sizes(self) -> list[int]:
        """The ping-pong int16 buffers: even layers read the first, odd ones the second."""
        widths = [self.layers[0].weights.shape[1]] + [layer.weights.shape[0] for layer in self.layers[:-1]]
        return [max(widths[0::2])] + ([max(widths[1::2])] if len(widths) > 1 else [])

    def ram_bytes(self) -> int:
        """RAM of the section's own buffers."""
        return 2 * sum(self.buffer_sizes())

    def c_includes(self, prefix: str) -> list[str]:
        """None: the section's C needs only the file's standard headers."""
        return []

    def c_lines(self, ctx: EmitContext) -> tuple[list[str], list[str]]:
        """The section's C and its int16 buffer declarations."""
        p = ctx.prefix
        qbufs = [f"{p}_q0", f"{p}_q1"]
        decls = [
            f"static int16_t {buf}[{size}];" for buf, size in zip(qbufs, self.buffer_sizes(), strict=False)
        ]
        src_ref, out_ref = ctx.ref(self.input), ctx.ref(self.output)
        scale = c_float(2.0**self.in_frac)
        lines = [
            f"/* 16-bit fixed point: {len(self.layers)} layer(s); "
            f"input with {self.in_frac} fractional bits */",
            f"for (uint32_t i = 0u; i < {self.layers[0].weights.shape[1]}u; ++i) {{",
            f"    if (!{p}_finite({src_ref}[i])) {{",
            f"        return {p}_safe(act, {p.upper()}_ERR_ACT_NOT_FINITE); "
            "/* never converted to an integer */",
            "    }",
            f"    float v = {src_ref}[i] * {scale};",
            "    v = (v > 32767.0f) ? 32767.0f : ((v < -32767.0f) ? -32767.0f : v);",
            "    v = v + 0.5f;",
            "    int32_t q = (int32_t)v;",
            "    if ((float)q > v) {",
            "        q -= 1; /* floor: round half up */",
            "    }",
            f"    {qbufs[0]}[i] = (int16_t)q;",
            "}",
        ]
        for j, layer in enumerate(self.layers):
            last = j == len(self.layers) - 1
            lines += layer.c_lines(ctx, qbufs[j % 2], out_ref if last else qbufs[(j + 1) % 2])
        return lines, decls


def _frac_for(peak: float) -> int:
    if peak <= 0 or not math.isfinite(peak):
        return 15
    return int(max(0, min(MAX_FRAC, math.floor(math.log2(Q_MAX / (peak * HEADROOM))))))


def _consumers(graph: Graph, value: str) -> list[Node]:
    return [n for n in graph.nodes if value in n.inputs]


def chain(graph: Graph, scheme: str = "q15") -> list[Node]:
    """The nodes an integer section replaces: the Gemm/MatMul layers joined by Relu, with only float ops
    that may run around it (``q15_float``) before and after; one line naming the node otherwise."""
    gemms = [i for i, n in enumerate(graph.nodes) if EMITTERS[n.op].linear]
    if not gemms:
        raise UnsupportedOpError(f"--quantize {scheme} needs at least one Gemm or MatMul")
    first, last = gemms[0], gemms[-1]
    for node in graph.nodes[:first]:
        if "before" not in EMITTERS[node.op].q15_float:
            raise UnsupportedOpError(
                f"{node.op} node '{node.name}' before the first layer is not supported with {scheme}"
            )
    for node in graph.nodes[last + 1 :]:
        if "after" not in EMITTERS[node.op].q15_float:
            raise UnsupportedOpError(
                f"{node.op} node '{node.name}' after the last layer is not supported with {scheme}"
            )
    inner = graph.nodes[first : last + 1]
    for i, node in enumerate(inner):
        if EMITTERS[node.op].linear:
            if i and not (inner[i - 1].op == "Relu" or EMITTERS[inner[i - 1].op].linear):
                raise UnsupportedOpError(
                    f"{scheme} layers may only be joined by Relu, found {inner[i - 1].op}"
                )
        elif node.op != "Relu":
            raise UnsupportedOpError(
                f"{node.op} node '{node.name}' between layers is not supported with {scheme} (only Relu)"
            )
        if node is not inner[-1] and len(_consumers(graph, node.outputs[0])) != 1:
            raise UnsupportedOpError(f"node '{node.name}': {scheme} layers must form a chain")
    return list(inner)


def plan(graph: Graph, calibration: np.ndarray) -> FixedSection:
    """Find the Gemm chain, calibrate its scales on ``calibration`` observations, quantise it."""
    inner = chain(graph)
    values = interpret.run(graph, calibration, "float64")
    section_input = inner[0].inputs[0]
    in_frac = _frac_for(float(np.max(np.abs(values[section_input]))))
    layers = []
    frac = in_frac
    nodes = [n for n in inner if n.op != "Relu"]
    for j, node in enumerate(nodes):
        affine = EMITTERS[node.op].affine(node, graph.constants)
        if affine.alpha != 1.0 or affine.beta != 1.0:
            raise UnsupportedOpError(f"Gemm node '{node.name}': alpha/beta != 1 are not supported with q15")
        w = affine.weights  # output-major [N][K]
        w_frac = np.array(
            [_frac_for(float(np.max(np.abs(row))) * 1.0 / HEADROOM) for row in w], dtype=np.int64
        )
        w_q = np.clip(np.rint(w * np.ldexp(1.0, w_frac)[:, None]), -Q_MAX, Q_MAX).astype(np.int16)
        bias = np.zeros(w.shape[0]) if affine.bias is None else affine.bias
        bias_acc = np.rint(bias * np.ldexp(1.0, frac + w_frac)).astype(np.int64)
        consumers = _consumers(graph, node.outputs[0])
        relu = bool(consumers) and consumers[0].op == "Relu" and j < len(nodes) - 1
        out_value = consumers[0].outputs[0] if relu else node.outputs[0]
        if j < len(nodes) - 1:
            out_frac = min(_frac_for(float(np.max(np.abs(values[out_value])))), frac + int(w_frac.min()) - 1)
        else:
            out_frac = None
        layers.append(Q15Layer(node.name, w_q, bias_acc, w_frac, frac, out_frac, relu))
        frac = out_frac if out_frac is not None else frac
    return FixedSection(
        section_input,
        inner[-1].outputs[0],
        in_frac,
        tuple(layers),
        frozenset(n.name for n in inner),
        inner[0].name,
    )


def quantize_input(x: np.ndarray, frac: int) -> np.ndarray:
    """float32 -> int16 as the C does it: scale (exact), clamp, round half up."""
    v = (np.asarray(x, F) * F(2.0**frac)).astype(F)
    v = np.where(v > F(Q_MAX), F(Q_MAX), np.where(v < F(-Q_MAX), F(-Q_MAX), v)).astype(F)
    return np.floor((v + F(0.5)).astype(F)).astype(np.int64)


def run(section: FixedSection, x: np.ndarray) -> np.ndarray:
    """The section on a batch of float32 inputs: int64 model, float32 output."""
    q = quantize_input(x, section.in_frac)
    for layer in section.layers[:-1]:
        q = layer.reference(q)
    return np.asarray(section.layers[-1].reference(q), dtype=F)
