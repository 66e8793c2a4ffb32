"""``--quantize int8``: full-integer int8 for the MLP chain, and its exact Python model.

The chain of Gemm/MatMul layers (with ReLU between them, see :func:`embedrl.export.fixed_point.chain`) runs
in integers, as TFLite Micro and CMSIS-NN run a quantised fully-connected layer:

- activations are int8 with a scale and a zero point per tensor, from the range the float64 graph reaches on
  the calibration observations (the export's verification observations; 0 always inside the range);
- weights are int8, symmetric per output channel (``s_w[n] = max|w[n]| / 127``);
- each output sums ``q_x[k] * q_w[n][k]`` into an int32 that starts at the bias in accumulator units
  (``s_x s_w[n]``) with the input's zero point folded in (``- zp_x * sum_k q_w[n][k]``, done at generation);
- a hidden layer requantises by the fixed-point multiplier and shift of ``s_x s_w[n] / s_out``
  (gemmlowp's SaturatingRoundingDoublingHighMul and RoundingDivideByPOT; one shift for the whole layer where
  every multiplier then keeps 24 significant bits, :func:`common_shift`), adds the output zero point and
  clamps to int8: the clamp's lower end is the ReLU;
- where the last layer feeds a Tanh or Sigmoid alone, its int32 sums are requantised (one rounding of the
  64-bit product) to int16 in Q3.12 and the non-linearity runs in int16 (:mod:`embedrl.export.ops.squash`:
  a 33-entry table with linear interpolation, worst error 1.5e-3), dequantised to float exactly; otherwise
  the sums become float (``(float)acc * s_x s_w[n]``). The action post-processing after it stays float.

Only the edges are float: the section's input is checked finite (else the safe action), scaled, offset by the
zero point, clamped and rounded into int8 once. Where the graph normalises the observation before the chain
(Sub, Div, Mul, Add by constants and Clip, as a VecNormalize export does), those float ops fold into that
one step (:class:`InputMap`): per feature one multiply, one add, a clamp and a round.

Integer sums are exact in any order, so the portable C (a dot product per output over an int16 copy of the
input, which gcc vectorises on the host) and the Cortex-M4/M7 DSP loop (``__sxtb16`` + ``__smlad``, two
multiply-adds per instruction) give the bits of the int64 NumPy model here. A layer whose scales the
encoding cannot hold (a multiplier exponent outside [-31, 30], a bias or a sum beyond int32) is refused,
naming the layer.
"""

from __future__ import annotations

import math
from dataclasses import dataclass, field

import numpy as np

from embedrl.export import interpret
from embedrl.export.contract.literals import c_float
from embedrl.export.errors import UnrepresentableRangeError, UnsupportedOpError
from embedrl.export.fixed_point import chain
from embedrl.export.ir import Graph, Node
from embedrl.export.ops import EMITTERS
from embedrl.export.ops.base import EmitContext
from embedrl.export.ops.linear import (
    INT8_MAX,
    INT8_MIN,
    INT32_MAX,
    SHIFT_RANGE,
    WORD,
    Int8Layer,
    dsp_condition,
    host_condition,
    host_row,
    padded,
    quantize_multiplier,
)
from embedrl.export.ops.squash import SQUASHES, input_step

F = np.float32
SCHEME = "int8"


@dataclass(frozen=True)
class Activation:
    """An int8 tensor's quantisation: ``real = scale * (q - zero)``."""

    scale: float
    zero: int


def activation_for(values: np.ndarray) -> Activation:
    """Scale and zero point covering the calibrated values and 0 (so a zero and the ReLU are exact)."""
    lo = min(0.0, float(np.min(values))) if values.size else 0.0
    hi = max(0.0, float(np.max(values))) if values.size else 0.0
    if not (math.isfinite(lo) and math.isfinite(hi)) or hi - lo <= 0:
        return Activation(1.0, 0)
    scale = (hi - lo) / (INT8_MAX - INT8_MIN)
    zero = int(np.clip(round(INT8_MIN - lo / scale), INT8_MIN, INT8_MAX))
    return Activation(scale, zero)


@dataclass(frozen=True)
class Given:
    """A quantisation the model carries (a QDQ model: :mod:`embedrl.export.qdq`), used, not calibrated."""

    activations: dict[str, Activation] = field(default_factory=dict)
    """Each quantised activation's scale and zero point, by float tensor name."""
    weight_scales: dict[str, np.ndarray] = field(default_factory=dict)
    """Each int8 weight's scales (one, or one per output channel), by the float constant's name."""

    def activation(self, tensor: str, layer: str) -> Activation:
        if tensor not in self.activations:
            raise UnsupportedOpError(
                f"{SCHEME}: the quantised model gives tensor '{tensor}' (layer '{layer}') no QuantizeLinear"
            )
        return self.activations[tensor]


FOLDABLE = frozenset({"Sub", "Div", "Mul", "Add", "Clip"})
"""Float ops before the chain that fold into the input quantisation (each an increasing or decreasing map of
every feature: an affine map by constants, or a clamp)."""


@dataclass(frozen=True)
class InputMap:
    """The section's float input -> int8, per feature: ``v = x * scale + offset`` (float32, in that order),
    ``v`` clamped to ``[low, high]``, rounded half up. ``scale`` and ``offset`` hold the folded normalisation
    and the quantisation's ``1 / s`` and zero point; ``[low, high]`` is within [-128, 127] and holds the
    folded clips (a clamp before an increasing map is a clamp after it, of the mapped bounds)."""

    scale: np.ndarray
    offset: np.ndarray
    low: np.ndarray
    high: np.ndarray
    """float32 [K] each."""

    def uniform(self) -> bool:
        """True when every feature has the same map (written as literals, not arrays, in the C)."""
        return all(bool(np.all(a == a[0])) for a in (self.scale, self.offset, self.low, self.high))


def plain_input(quant: Activation, width: int) -> InputMap:
    """The input map of the quantisation alone: ``x / s + zero`` within [-128, 127]."""
    return InputMap(
        np.full(width, F(1.0) / F(quant.scale), F),
        np.full(width, quant.zero, F),
        np.full(width, INT8_MIN, F),
        np.full(width, INT8_MAX, F),
    )


@dataclass(frozen=True)
class _Prefix:
    """The float ops before the chain as one map per feature: ``clamp(a * x + c, low, high)`` (float64)."""

    nodes: tuple[str, ...]
    a: np.ndarray
    c: np.ndarray
    low: np.ndarray
    high: np.ndarray

    def then_affine(self, p: np.ndarray, q: np.ndarray) -> _Prefix:
        """This map followed by ``p * y + q`` (``p`` never 0)."""
        lo, hi = p * self.low + q, p * self.high + q
        return _Prefix(
            self.nodes, self.a * p, self.c * p + q, np.where(p > 0, lo, hi), np.where(p > 0, hi, lo)
        )

    def then_clip(self, lo: float, hi: float) -> _Prefix:
        """This map followed by ``min(max(y, lo), hi)`` (the C's order): the bounds clamped the same way."""
        return _Prefix(
            self.nodes,
            self.a,
            self.c,
            np.minimum(np.maximum(self.low, lo), hi),
            np.minimum(np.maximum(self.high, lo), hi),
        )

    def input_map(self, quant: Activation) -> InputMap:
        """The map then the quantisation ``y / s + zero`` and the int8 range, in float32."""
        inv = 1.0 / quant.scale

        def bound(v: np.ndarray) -> np.ndarray:
            return np.clip(v * inv + quant.zero, INT8_MIN, INT8_MAX).astype(F)

        return InputMap(
            (self.a * inv).astype(F), (self.c * inv + quant.zero).astype(F), bound(self.low), bound(self.high)
        )


def _fold_prefix(graph: Graph, first: str) -> _Prefix | None:
    """The float ops from the graph's input to the chain's first node ``first`` as one :class:`_Prefix`, or
    None when there are none or one of them does not fold (another op, a branch, a non-constant or
    non-finite operand, a factor of 0, a divisor as the data operand)."""
    index = next(i for i, n in enumerate(graph.nodes) if n.name == first)
    nodes = graph.nodes[:index]
    width = int(graph.shapes[graph.input][-1])
    if not nodes:
        return None
    ones = np.ones(width)
    prefix, current = _Prefix((), ones, 0.0 * ones, -np.inf * ones, np.inf * ones), graph.input
    for node in nodes:
        users = [n for n in graph.nodes if node.outputs[0] in n.inputs]
        if node.op not in FOLDABLE or (node.op in ("Div", "Clip") and node.inputs[0] != current):
            return None
        if len(users) != 1 or current not in node.inputs:
            return None
        step = _fold_node(graph, node, current, prefix, width)
        if step is None:
            return None
        prefix, current = step, node.outputs[0]
    return _Prefix(tuple(n.name for n in nodes), prefix.a, prefix.c, prefix.low, prefix.high)


def _fold_node(graph: Graph, node: Node, current: str, prefix: _Prefix, width: int) -> _Prefix | None:
    """``prefix`` followed by ``node`` (one of :data:`FOLDABLE`, reading ``current``), or None."""
    if node.op == "Clip":
        names = [*node.inputs[1:3], "", ""][:2]
        if any(name and name not in graph.constants for name in names):
            return None
        lo, hi = (
            float(graph.constants[name].reshape(-1)[0]) if name else default
            for name, default in zip(names, (-math.inf, math.inf), strict=True)
        )
        return prefix.then_clip(lo, hi)
    other = node.inputs[1] if node.inputs[0] == current else node.inputs[0]
    if other not in graph.constants or other == current:
        return None
    k = np.asarray(graph.constants[other], np.float64).reshape(-1)
    if k.size not in (1, width) or not np.all(np.isfinite(k)):
        return None
    k = np.broadcast_to(k, (width,))
    data_first = node.inputs[0] == current
    ones, zeros = np.ones(width), np.zeros(width)
    if node.op == "Add":
        p, q = ones, k
    elif node.op == "Sub":
        p, q = (ones, -k) if data_first else (-ones, k)
    elif node.op == "Mul":
        p, q = k, zeros
    elif np.any(k == 0):  # Div by 0: not a scale
        return None
    else:
        p, q = 1.0 / k, zeros
    if not np.all(np.isfinite(p)) or np.any(p == 0):
        return None
    return prefix.then_affine(p, q)


@dataclass(frozen=True)
class IntegerSection:
    """The integer part of the graph: from ``input`` (float, quantised on entry) to ``output`` (float)."""

    input: str
    output: str
    quant: Activation
    """The chain's input quantisation (of the normalised observation, where normalisation folds in)."""
    input_map: InputMap
    """How the section's input becomes int8 (the folded float ops and ``quant``)."""
    layers: tuple[Int8Layer, ...]
    nodes: frozenset[str]
    """Names of the IR nodes the section replaces."""
    first_node: str
    folded: tuple[str, ...] = ()
    """The float ops before the chain folded into :attr:`input_map`, in order."""

    def run(self, x: np.ndarray) -> np.ndarray:
        """The section on a batch of float32 inputs: int64 model, float32 output."""
        q = map_input(x, self.input_map)
        for layer in self.layers[:-1]:
            q = layer.reference(q)
        return np.asarray(self.layers[-1].reference(q), dtype=F)

    def widths(self) -> list[int]:
        """The int8 input width of every layer."""
        return [int(layer.weights.shape[1]) for layer in self.layers]

    def outputs(self) -> int:
        """The widest layer output (the DSP loop's sums)."""
        return max(int(layer.weights.shape[0]) for layer in self.layers)

    def buffer_sizes(self) -> list[int]:
        """The ping-pong int8 buffers (whole words): even layers read the first, odd ones the second."""
        widths = [padded(w) for w in self.widths()]
        return [max(widths[0::2])] + ([max(widths[1::2])] if len(widths) > 1 else [])

    def ram_bytes(self) -> int:
        """RAM of the int8 buffers and of a layer input as int16 (on DSP cores its pairs in whole words, on
        x86-64 the host loop's padded copy and its int32 sums): the largest build's."""
        pairs = max(padded(w) for w in self.widths()) // WORD
        host = 2 * max(host_row(w) for w in self.widths()) + 4 * self.outputs()
        return sum(self.buffer_sizes()) + max(2 * 4 * pairs, host)

    def c_includes(self, prefix: str) -> list[str]:
        """The ACLE header of the DSP loop, on the cores that have it, among the file's includes."""
        return [f"#if {dsp_condition(prefix)}", "#include <arm_acle.h>", "#endif"]

    def c_lines(self, ctx: EmitContext) -> tuple[list[str], list[str]]:
        """The section's C and the declarations of its buffers (and of the DSP switch)."""
        p, up = ctx.prefix, ctx.prefix.upper()
        qbufs = [f"{p}_q0", f"{p}_q1"]
        pairs = max(padded(w) for w in self.widths()) // WORD
        decls = [
            "/* The DSP loop on cores with the ACLE SIMD32 intrinsics (Cortex-M4, M7); on x86-64 the host",
            f" * loop; elsewhere, or with -D{up}_PORTABLE, the portable loop. All give the same bits",
            " * (integer sums). */",
            f"#if {dsp_condition(p)}",
            f"#define {up}_DSP 1",
            f"static int32_t {p}_pairs[{2 * pairs}]; /* per input word: its even, then odd bytes (int16) */",
            "#else",
            f"#define {up}_DSP 0",
            "#endif",
            f"#if {host_condition(p)}",
            f"static int16_t {p}_wide[{max(host_row(w) for w in self.widths())}]; /* a layer's input */",
            f"static int32_t {p}_sums[{self.outputs()}]; /* a layer's sums */",
            "#endif",
            *(f"static int8_t {buf}[{size}];" for buf, size in zip(qbufs, self.buffer_sizes(), strict=False)),
        ]
        src_ref, out_ref = ctx.ref(self.input), ctx.ref(self.output)
        lines = [
            f"/* full-integer int8: {len(self.layers)} layer(s); input scale {self.quant.scale:.9g}, "
            f"zero point {self.quant.zero} */",
            *self._input_lines(ctx, src_ref, qbufs[0]),
        ]
        for j, layer in enumerate(self.layers):
            last = j == len(self.layers) - 1
            dst = out_ref if last else qbufs[(j + 1) % 2]
            lines += layer.c_lines(ctx, qbufs[j % 2], dst, (f"{p}_pairs", f"{p}_wide", f"{p}_sums"))
        return lines, decls

    def _input_lines(self, ctx: EmitContext, src: str, dst: str) -> list[str]:
        """The section's input checked finite and mapped to int8 (:class:`InputMap`): literals when every
        feature has the same map, else arrays of the folded normalisation."""
        p, m = ctx.prefix, self.input_map
        if m.uniform():
            scale, offset, low, high = (c_float(float(a[0])) for a in (m.scale, m.offset, m.low, m.high))
            note = ""
        else:
            arrays = zip(("scale", "offset", "low", "high"), (m.scale, m.offset, m.low, m.high), strict=True)
            scale, offset, low, high = (
                f"{ctx.const(f'input_{what}#int8', a, f'int8 input map: {what} per feature [{a.size}]')}[i]"
                for what, a in arrays
            )
            note = f"    /* the float ops before the chain folded in: {', '.join(self.folded)} */"
        return [
            f"for (uint32_t i = 0u; i < {self.widths()[0]}u; ++i) {{",
            *([note] if note else []),
            f"    if (!{p}_finite({src}[i])) {{",
            f"        return {p}_safe(act, {p.upper()}_ERR_ACT_NOT_FINITE); "
            "/* never converted to an integer */",
            "    }",
            f"    float v = {src}[i] * {scale};",
            f"    v = v + {offset};",
            f"    v = (v > {high}) ? {high} : ((v < {low}) ? {low} : v);",
            "    v = v + 0.5f;",
            "    int32_t q = (int32_t)v;",
            "    if ((float)q > v) {",
            "        q -= 1; /* floor: round half up */",
            "    }",
            f"    {dst}[i] = (int8_t)q;",
            "}",
        ]


def map_input(x: np.ndarray, m: InputMap) -> np.ndarray:
    """float32 -> int8 as the C does it (:class:`InputMap`): times the scale, plus the offset, clamp, round
    half up."""
    v = (np.asarray(x, F) * m.scale).astype(F)
    v = (v + m.offset).astype(F)
    v = np.where(v > m.high, m.high, np.where(v < m.low, m.low, v)).astype(F)
    return np.floor((v + F(0.5)).astype(F)).astype(np.int64)


def quantize_input(x: np.ndarray, quant: Activation) -> np.ndarray:
    """float32 -> int8 by the quantisation alone (the chain's input, no folded ops), as the C does it."""
    return map_input(x, plain_input(quant, np.asarray(x).shape[-1]))


def plan(graph: Graph, calibration: np.ndarray, given: Given | None = None) -> IntegerSection:
    """Find the Gemm chain, calibrate its activations on ``calibration`` observations (or take them and the
    weights' scales from ``given``), quantise it; refuse a layer whose scales do not fit the encoding
    (:class:`UnrepresentableRangeError`, naming it)."""
    inner = chain(graph, SCHEME)
    values = interpret.run(graph, calibration, "float64") if given is None else {}
    chain_input = inner[0].inputs[0]
    quant = _activation(chain_input, inner[0].name, values, given)
    # a QDQ model's quantised tensors are compared with onnxruntime's one by one: its float ops stay
    prefix = _fold_prefix(graph, inner[0].name) if given is None else None
    if prefix is None:
        section_input, first, input_map = (
            chain_input,
            inner[0].name,
            plain_input(quant, graph.size(chain_input)),
        )
    else:
        section_input, first, input_map = graph.input, prefix.nodes[0], prefix.input_map(quant)
    squash = _squash(graph, inner[-1]) if given is None else None
    in_quant = quant
    nodes = [n for n in inner if n.op != "Relu"]
    layers = []
    for j, node in enumerate(nodes):
        affine = EMITTERS[node.op].affine(node, graph.constants)
        if affine.alpha != 1.0 or affine.beta != 1.0:
            raise UnsupportedOpError(
                f"Gemm node '{node.name}': alpha/beta != 1 are not supported with {SCHEME}"
            )
        w = affine.weights  # output-major [N][K]
        w_q, w_scale = _int8_weights(
            node.name, w, None if given is None else given.weight_scales.get(node.inputs[1])
        )
        acc_scale = in_quant.scale * w_scale
        bias = np.zeros(w.shape[0]) if affine.bias is None else affine.bias
        bias_acc = np.rint(bias / acc_scale)
        _check_accumulator(node.name, bias_acc, w_q)
        bias_q = bias_acc.astype(np.int64) - in_quant.zero * w_q.sum(axis=1)
        consumers = [n for n in graph.nodes if node.outputs[0] in n.inputs]
        last = j == len(nodes) - 1
        relu = not last and consumers[0].op == "Relu"
        if last and squash is not None:
            multiplier, shift = _multipliers(node.name, acc_scale / input_step(squash.op))
            layer = Int8Layer(
                node.name, w_q.astype(np.int8), bias_q, multiplier, shift, 0, False, None, squash.op
            )
        elif last:
            none = np.zeros(0, np.int64)
            layer = Int8Layer(
                node.name, w_q.astype(np.int8), bias_q, none, none, 0, False, acc_scale.astype(F)
            )
        else:
            out = _activation(consumers[0].outputs[0] if relu else node.outputs[0], node.name, values, given)
            multiplier, shift = common_shift(
                acc_scale / out.scale, *_multipliers(node.name, acc_scale / out.scale)
            )
            layer = Int8Layer(node.name, w_q.astype(np.int8), bias_q, multiplier, shift, out.zero, relu, None)
            in_quant = out
        layers.append(layer)
    return IntegerSection(
        section_input,
        (squash or inner[-1]).outputs[0],
        quant,
        input_map,
        tuple(layers),
        frozenset(n.name for n in [*inner, *([squash] if squash else [])])
        | frozenset(prefix.nodes if prefix else ()),
        first,
        prefix.nodes if prefix else (),
    )


def _squash(graph: Graph, last: Node) -> Node | None:
    """The Tanh or Sigmoid the chain's last layer feeds alone, which then runs in int16 (:mod:`.squash`)."""
    users = [n for n in graph.nodes if last.outputs[0] in n.inputs]
    if len(users) == 1 and users[0].op in SQUASHES and last.outputs[0] != graph.output:
        return users[0]
    return None


def _activation(tensor: str, layer: str, values: dict[str, np.ndarray], given: Given | None) -> Activation:
    """A tensor's quantisation: the model's own, or calibrated from its values."""
    return activation_for(values[tensor]) if given is None else given.activation(tensor, layer)


WEIGHT_GRID_TOLERANCE = 1e-3
"""How far (in steps) a given weight may sit from its int8 grid point: float32 rounding, never a step."""


def _int8_weights(layer: str, w: np.ndarray, scales: np.ndarray | None) -> tuple[np.ndarray, np.ndarray]:
    """Symmetric per-output-channel int8 weights and their scales: ``max|w[n]| / 127``, or the model's own
    scales (which must put every weight on the int8 grid of its output channel)."""
    if scales is None:
        peak = np.max(np.abs(w), axis=1)
        w_scale = np.where(peak > 0, peak / INT8_MAX, 1.0)
        return np.clip(np.rint(w / w_scale[:, None]), -INT8_MAX, INT8_MAX).astype(np.int64), w_scale
    fits = scales.size in (1, w.shape[0]) and bool(np.all(scales > 0))
    given = np.broadcast_to(np.asarray(scales, np.float64), (w.shape[0],)) if fits else np.ones(w.shape[0])
    steps = w / given[:, None]
    if (
        not fits
        or np.max(np.abs(steps - np.rint(steps))) > WEIGHT_GRID_TOLERANCE
        or np.max(np.abs(steps)) > INT8_MAX + 0.5
    ):
        raise UnsupportedOpError(
            f"{SCHEME}: layer '{layer}': the model's int8 weights are not quantised per output channel "
            f"({scales.size} scale(s) for {w.shape[0]} outputs)"
        )
    return np.rint(steps).astype(np.int64), np.array(given)


def _check_accumulator(layer: str, bias_acc: np.ndarray, w_q: np.ndarray) -> None:
    """The bias in accumulator units, and every sum from it, within int32 for any int8 input."""
    worst = np.abs(bias_acc) + 128.0 * (np.abs(w_q).sum(axis=1) + np.abs(w_q.sum(axis=1)))
    if not np.all(np.isfinite(bias_acc)) or np.any(worst > INT32_MAX):
        n = int(np.argmax(np.where(np.isfinite(worst), worst, np.inf)))
        raise UnrepresentableRangeError(
            f"{SCHEME}: layer '{layer}' output {n}: its bias ({bias_acc[n]:.3g} in accumulator units) "
            "and sums do not fit an int32 accumulator at the calibrated input scale"
        )


COMMON_SHIFT_BITS = 24
"""Significant bits each multiplier keeps at least when a layer's channels share one shift (a float32
scale's): the shift then is a constant of the code, not a table."""


def common_shift(real: np.ndarray, m: np.ndarray, shift: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """A hidden layer's requantisation with one shift for every channel, the largest, each multiplier
    ``round(real * 2^(31 - shift))`` below 2^31 keeping at least :data:`COMMON_SHIFT_BITS` significant bits;
    the per-channel pairs ``(m, shift)`` as they are where a channel would keep fewer."""
    top = int(np.max(shift))
    common = np.rint(np.asarray(real, np.float64) * 2.0 ** (31 - top)).astype(np.int64)
    if np.any(common >= 2**31) or np.any(common < 2 ** (COMMON_SHIFT_BITS - 1)):
        return m, shift
    return common, np.full_like(shift, top)


def _multipliers(layer: str, real: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """Each channel's requantisation scale as a Q31 multiplier and a shift, or the one-line refusal."""
    encoded = []
    for n, r in enumerate(real):
        pair = quantize_multiplier(float(r))
        if pair is None:
            raise UnrepresentableRangeError(
                f"{SCHEME}: layer '{layer}' output {n}: requantisation scale {float(r):.3g} cannot be "
                f"represented (a Q31 multiplier with a shift in [{SHIFT_RANGE[0]}, {SHIFT_RANGE[1]}])"
            )
        encoded.append(pair)
    return np.array([m for m, _ in encoded], np.int64), np.array([s for _, s in encoded], np.int64)
