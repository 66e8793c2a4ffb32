"""Recurrent cells: LSTM and GRU, one time step of batch 1 (ONNX semantics, forward direction).

A policy with memory runs one step per control period: the sequence is the episode, and the cell's state
comes in as graph values (``initial_h``, ``initial_c``) and leaves as its outputs (``Y_h``, ``Y_c``), which
the generated module keeps in static storage between steps (see :attr:`embedrl.export.ir.Graph.states`).

Gate pre-activations sum in a fixed order, bias first, then the input's terms, then the hidden state's;
sigmoid and tanh are the deterministic helpers, so the C gives the same bits at every optimisation level and
on every C library, and the models here (``float32_model``, and ``reference`` in ``int8``) are bit for bit
that C. With ``--quantize int8`` the input and recurrent matrices are int8 with a scale per row (the scheme of
:mod:`embedrl.export.quantize`): each term sums its products, then adds ``scale * sum`` to the bias.
"""

from __future__ import annotations

from collections.abc import Mapping, Sequence
from dataclasses import dataclass
from typing import ClassVar

import numpy as np

from embedrl.export.ir import AttrValue, Node
from embedrl.export.ops.base import EmitContext, Emitter, F, Interval, Shape, _fail
from embedrl.export.ops.deterministic import sigmoid_det, tanh_det
from embedrl.export.ops.linear import quantize_columns

X, W, R, B, SEQUENCE_LENS, INITIAL_H, INITIAL_C, PEEPHOLES = range(8)
"""Input positions of ONNX's LSTM (GRU has the first six)."""


def _strings(value: AttrValue) -> tuple[str, ...]:
    items = value if isinstance(value, tuple) else (value,)
    return tuple(str(v) for v in items)


@dataclass(frozen=True)
class Matrices:
    """A cell's weights as its C holds them: float32, or int8 values (here as float32) with a float32 scale
    per row (``--quantize int8``); the biases stay float32."""

    w: np.ndarray
    """[G*H, I]"""
    r: np.ndarray
    """[G*H, H]"""
    w_scale: np.ndarray | None
    r_scale: np.ndarray | None
    b: np.ndarray
    """[2, G*H]: the input and the recurrent bias."""


class Recurrent(Emitter):
    """What LSTM and GRU share: validation, weights per gate, and the matrix-vector sums of the C."""

    gates: ClassVar[int]
    default_activations: ClassVar[tuple[str, ...]]
    attrs: ClassVar[Mapping[str, AttrValue]] = {
        "hidden_size": 0,
        "direction": "forward",
        "activations": (),
        "layout": 0,
    }
    min_inputs = 3
    bounded_by_itself = True  # h = o * tanh(c), or a mix of tanh and the previous h: see bounds()

    def shape(self, node: Node, shapes: Mapping[str, Shape], constants: Mapping[str, np.ndarray]) -> Shape:
        hidden = int(node.attr("hidden_size", 0))
        if hidden <= 0:
            raise _fail(node, "needs a positive hidden_size")
        if node.attr("direction", "forward") != "forward" or int(node.attr("layout", 0)) != 0:
            raise _fail(node, "only direction=forward with layout=0 is supported")
        activations = _strings(node.attr("activations", ()))
        if activations and tuple(a.lower() for a in activations) != self.default_activations:
            raise _fail(node, f"only the default activations {list(self.default_activations)} are supported")
        x = shapes[node.inputs[X]]
        if len(x) != 3 or x[0] != 1 or x[1] != 1:
            raise _fail(node, f"input X must be [1, 1, features] (one step, batch 1), got {list(x)}")
        features = x[2]
        expect = {
            W: (1, self.gates * hidden, features),
            R: (1, self.gates * hidden, hidden),
            B: (1, 2 * self.gates * hidden),
        }
        for position, shape in expect.items():
            name = node.inputs[position] if position < len(node.inputs) else ""
            if position == B and not name:
                continue
            if name not in constants:
                raise _fail(node, f"input {position} ('{name}') must be a constant of shape {list(shape)}")
            if constants[name].shape != shape:
                raise _fail(
                    node, f"input '{name}' has shape {list(constants[name].shape)}, expected {list(shape)}"
                )
        if len(node.inputs) > SEQUENCE_LENS and node.inputs[SEQUENCE_LENS]:
            raise _fail(node, "sequence_lens is not supported (one step per call)")
        for position in self.state_inputs:
            name = node.inputs[position] if position < len(node.inputs) else ""
            if not name:
                raise _fail(
                    node, f"input {position} (initial state) is required: the state is carried by the graph"
                )
            if name in constants or tuple(shapes[name]) != (1, 1, hidden):
                raise _fail(node, f"initial state '{name}' must be a runtime value of shape [1, 1, {hidden}]")
        return (1, 1, 1, hidden)

    state_inputs: ClassVar[tuple[int, ...]]

    def bounds(self, node: Node, x: Interval, constants: Mapping[str, np.ndarray], size: int) -> Interval:
        """The hidden state (``Y``, ``Y_h``) is within [-1, 1] for any input: an LSTM's is ``o * tanh(c)``, a
        GRU's a mix of a tanh and the hidden state before it, which is within [-1, 1] from a zero reset on."""
        return np.full(size, -1.0), np.full(size, 1.0)

    def later_bounds(self, node: Node, first: Interval, sizes: Sequence[int]) -> list[Interval]:
        """``Y_h`` is ``Y``; an LSTM's cell state ``Y_c`` is unbounded."""
        unbounded = super().later_bounds(node, first, sizes)
        return [(first[0].copy(), first[1].copy()), *unbounded[1:]]

    def output_shapes(self, node: Node, first: Shape) -> tuple[Shape, ...]:
        hidden = first[-1]
        return ((1, 1, 1, hidden), *((1, 1, hidden),) * (len(node.outputs) - 1))

    def weights(
        self, node: Node, constants: Mapping[str, np.ndarray]
    ) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
        """W [G*H, I], R [G*H, H] (float32) and the two biases [2, G*H] (zeros when absent)."""
        w = np.asarray(constants[node.inputs[W]], F)[0]
        r = np.asarray(constants[node.inputs[R]], F)[0]
        rows = w.shape[0]
        name = node.inputs[B] if len(node.inputs) > B else ""
        b = np.asarray(constants[name], F).reshape(2, rows) if name else np.zeros((2, rows), F)
        return w, r, b

    def matrices(self, node: Node, constants: Mapping[str, np.ndarray], precision: str) -> Matrices:
        """The cell's matrices as the C of ``precision`` holds them (``int8``: quantised per row)."""
        w, r, b = self.weights(node, constants)
        if precision != "int8":
            return Matrices(w, r, None, None, b)
        (qw, sw), (qr, sr) = (quantize_columns(m.T) for m in (w, r))
        return Matrices(qw.T.astype(F), qr.T.astype(F), sw, sr, b)

    def _declare(self, node: Node, ctx: EmitContext, m: Matrices, names: str) -> tuple[str, str, str, str]:
        """The C symbols of W, R and (int8) their per-row scales."""
        kind = "int8, " if m.w_scale is not None else ""
        symbols = []
        for key, matrix, what in (("W", m.w, "input"), ("R", m.r, "recurrent")):
            stored = matrix.astype(np.int8) if m.w_scale is not None else matrix
            symbols.append(
                ctx.const(
                    f"{node.name}#{key}",
                    stored,
                    f"{node.op} '{node.name}' {what} weights, {kind}gates {names}",
                )
            )
        if m.w_scale is None or m.r_scale is None:
            return symbols[0], symbols[1], "", ""
        sw = ctx.const(
            f"{node.name}#Wscale", m.w_scale, f"{node.op} '{node.name}' input weights' scale per row"
        )
        sr = ctx.const(
            f"{node.name}#Rscale", m.r_scale, f"{node.op} '{node.name}' recurrent weights' scale per row"
        )
        return symbols[0], symbols[1], sw, sr

    def float32_model(
        self, node: Node, inputs: Sequence[np.ndarray], constants: Mapping[str, np.ndarray]
    ) -> np.ndarray:
        """Bit for bit what the float32 C computes (outputs stacked as ``reference`` stacks them)."""
        raise NotImplementedError

    @staticmethod
    def sum_c(
        out: str, bias: str, terms: Sequence[tuple[str, str, str, int]], row: str, tag: str
    ) -> list[str]:
        """C setting ``out`` to ``bias`` plus each (matrix, its per-row scale or "", vector, length) term:
        float weights add every product to one sum in order; int8 weights sum each term's products (in
        ``{tag}_sum0``, ...), then add ``scale * sum`` (the scheme of :mod:`embedrl.export.quantize`)."""
        if not any(scale for _, scale, _, _ in terms):
            lines = [f"{out} = {bias};"]
            for matrix, _, vector, length in terms:
                lines += [
                    f"for (uint32_t k = 0u; k < {length}u; ++k) {{",
                    f"    {out} += {matrix}[{row}][k] * {vector};",
                    "}",
                ]
            return lines
        lines, parts = [], []
        for t, (matrix, scale, vector, length) in enumerate(terms):
            lines += [
                f"float {tag}_sum{t} = 0.0f;",
                f"for (uint32_t k = 0u; k < {length}u; ++k) {{",
                f"    {tag}_sum{t} += (float){matrix}[{row}][k] * {vector};",
                "}",
            ]
            parts.append(f"({scale}[{row}] * {tag}_sum{t})")
        return [*lines, f"{out} = {bias} + {' + '.join(parts)};"]

    @staticmethod
    def sums32(
        bias: np.ndarray, terms: Sequence[tuple[np.ndarray, np.ndarray | None, np.ndarray]]
    ) -> np.ndarray:
        """float32 model of :meth:`sum_c` for a batch: ``bias`` [N], terms of (matrix [N, K], its scale [N] or
        None, vector [B, K])."""
        rows = len(bias)

        def chain(start: np.ndarray, matrix: np.ndarray, vector: np.ndarray) -> np.ndarray:
            acc = start
            for k in range(matrix.shape[1]):
                acc = (acc + (matrix[:, k][None, :] * vector[:, k : k + 1]).astype(F)).astype(F)
            return acc

        start = np.broadcast_to(np.asarray(bias, F), (len(terms[0][2]), rows)).astype(F)
        if all(scale is None for _, scale, _ in terms):
            for matrix, _, vector in terms:
                start = chain(start, matrix, vector)
            return start
        out = start
        for matrix, scale, vector in terms:
            assert scale is not None
            out = (out + (scale * chain(np.zeros_like(start), matrix, vector)).astype(F)).astype(F)
        return out

    def _outputs_c(self, node: Node, ctx: EmitContext, values: Sequence[str]) -> list[str]:
        """Copy the next state into the outputs: ``Y`` and ``Y_h`` get h, ``Y_c`` gets c."""
        lines = []
        for out, value in zip(node.outputs, values, strict=False):
            if out:
                lines.append(f"    {ctx.ref(out)}[j] = {value};")
        return lines


class LSTM(Recurrent):
    """ONNX LSTM (gates i, o, f, c): ``c' = f*c + i*tanh(.)``, ``h' = o*tanh(c')``; no peepholes, no clip."""

    gates = 4
    default_activations = ("sigmoid", "tanh", "tanh")
    attrs: ClassVar[Mapping[str, AttrValue]] = {**Recurrent.attrs, "input_forget": 0}
    max_inputs = 8
    max_outputs = 3
    state_inputs = (INITIAL_H, INITIAL_C)

    def shape(self, node: Node, shapes: Mapping[str, Shape], constants: Mapping[str, np.ndarray]) -> Shape:
        if int(node.attr("input_forget", 0)) != 0:
            raise _fail(node, "input_forget=1 is not supported")
        if len(node.inputs) > PEEPHOLES and node.inputs[PEEPHOLES]:
            raise _fail(node, "peephole weights (input P) are not supported")
        return super().shape(node, shapes, constants)

    def reference(
        self, node: Node, inputs: Sequence[np.ndarray], constants: Mapping[str, np.ndarray], precision: str
    ) -> np.ndarray:
        x, h, c = inputs[0], inputs[-2], inputs[-1]
        if precision == "float64":
            w, r, b = self.weights(node, constants)
            h_next, c_next = self.exact(
                x.astype(np.float64), h.astype(np.float64), c.astype(np.float64), w, r, b
            )
        else:
            h_next, c_next = self.step32(
                self.matrices(node, constants, precision), x.astype(F), h.astype(F), c.astype(F)
            )
        return np.stack([h_next, h_next, c_next][: len(node.outputs)])

    def float32_model(
        self, node: Node, inputs: Sequence[np.ndarray], constants: Mapping[str, np.ndarray]
    ) -> np.ndarray:
        """Bit for bit what the float32 C computes (outputs stacked as :meth:`reference` stacks them)."""
        x, h, c = inputs[0], inputs[-2], inputs[-1]
        h_next, c_next = self.step32(
            self.matrices(node, constants, "float32"), x.astype(F), h.astype(F), c.astype(F)
        )
        return np.stack([h_next, h_next, c_next][: len(node.outputs)])

    @staticmethod
    def exact(
        x: np.ndarray, h: np.ndarray, c: np.ndarray, w: np.ndarray, r: np.ndarray, b: np.ndarray
    ) -> tuple[np.ndarray, np.ndarray]:
        """The cell's meaning in float64: the next (h, c)."""
        z = x @ w.T.astype(np.float64) + h @ r.T.astype(np.float64) + b.astype(np.float64).sum(0)
        i, o, f, g = np.split(z, 4, axis=1)

        def sigmoid(v: np.ndarray) -> np.ndarray:
            return np.asarray(1.0 / (1.0 + np.exp(-v)))

        c_next = sigmoid(f) * c + sigmoid(i) * np.tanh(g)
        return sigmoid(o) * np.tanh(c_next), c_next

    def step32(
        self, m: Matrices, x: np.ndarray, h: np.ndarray, c: np.ndarray
    ) -> tuple[np.ndarray, np.ndarray]:
        """Bit for bit what the generated C (float32 or int8 weights) computes: the next (h, c)."""
        hidden = m.r.shape[1]
        acc = self.sums32((m.b[0] + m.b[1]).astype(F), [(m.w, m.w_scale, x), (m.r, m.r_scale, h)])
        i, o, f, g = (acc[:, k * hidden : (k + 1) * hidden] for k in range(4))
        c_next = ((sigmoid_det(f) * c).astype(F) + (sigmoid_det(i) * tanh_det(g)).astype(F)).astype(F)
        return (sigmoid_det(o) * tanh_det(c_next)).astype(F), c_next

    def emit(self, node: Node, ctx: EmitContext, n: int) -> list[str]:
        constants = {k: ctx.constant(k) for k in node.inputs[W : B + 1] if k}
        m = self.matrices(node, constants, "int8" if ctx.quantize else "float32")  # type: ignore[arg-type]
        wc, rc, sw, sr = self._declare(node, ctx, m, "i, o, f, c")
        bc = ctx.const(
            f"{node.name}#B", (m.b[0] + m.b[1]).astype(F), f"LSTM '{node.name}' bias (input + recurrent)"
        )
        x, h, c = (ctx.ref(node.inputs[p]) for p in (X, INITIAL_H, INITIAL_C))
        sig, tanh = ctx.helper("sigmoid_det"), ctx.helper("tanh_det")
        features = ctx.size(node.inputs[X])
        row = f"(g * {n}u) + j"
        sums = self.sum_c(
            "acc[g]", f"{bc}[{row}]", [(wc, sw, f"{x}[k]", features), (rc, sr, f"{h}[k]", n)], row, "gate"
        )
        return [
            f"for (uint32_t j = 0u; j < {n}u; ++j) {{",
            f"    float acc[{self.gates}];",
            f"    for (uint32_t g = 0u; g < {self.gates}u; ++g) {{",
            *("        " + line for line in sums),
            "    }",
            f"    const float c_next = ({sig}(acc[2]) * {c}[j]) + ({sig}(acc[0]) * {tanh}(acc[3]));",
            f"    const float h_next = {sig}(acc[1]) * {tanh}(c_next);",
            *self._outputs_c(node, ctx, ("h_next", "h_next", "c_next")),
            "}",
        ]


class GRU(Recurrent):
    """ONNX GRU (gates z, r, h): ``h' = (1 - z)*n + z*h``; the candidate's recurrent term inside the reset
    gate (``linear_before_reset=1``, PyTorch's ``nn.GRU``) or its input (0, ONNX's default)."""

    gates = 3
    default_activations = ("sigmoid", "tanh")
    attrs: ClassVar[Mapping[str, AttrValue]] = {**Recurrent.attrs, "linear_before_reset": 0}
    max_inputs = 6
    max_outputs = 2
    state_inputs = (INITIAL_H,)

    def reference(
        self, node: Node, inputs: Sequence[np.ndarray], constants: Mapping[str, np.ndarray], precision: str
    ) -> np.ndarray:
        x, h = inputs[0], inputs[-1]
        before = int(node.attr("linear_before_reset", 0)) != 0
        if precision == "float64":
            h_next = self._exact(
                x.astype(np.float64), h.astype(np.float64), *self.weights(node, constants), before
            )
        else:
            h_next = self.step32(self.matrices(node, constants, precision), x.astype(F), h.astype(F), before)
        return np.stack([h_next, h_next][: len(node.outputs)])

    def float32_model(
        self, node: Node, inputs: Sequence[np.ndarray], constants: Mapping[str, np.ndarray]
    ) -> np.ndarray:
        """Bit for bit what the float32 C computes (outputs stacked as :meth:`reference` stacks them)."""
        before = int(node.attr("linear_before_reset", 0)) != 0
        m = self.matrices(node, constants, "float32")
        h_next = self.step32(m, inputs[0].astype(F), inputs[-1].astype(F), before)
        return np.stack([h_next, h_next][: len(node.outputs)])

    @staticmethod
    def _exact(
        x: np.ndarray, h: np.ndarray, w: np.ndarray, r: np.ndarray, b: np.ndarray, before: bool
    ) -> np.ndarray:
        w, r, b = (a.astype(np.float64) for a in (w, r, b))
        hidden = r.shape[1]
        wx = x @ w.T + b[0]
        wz, wr, wn = np.split(wx, 3, axis=1)
        rz, rr, _ = np.split(h @ r.T + b[1], 3, axis=1)
        z, reset = 1.0 / (1.0 + np.exp(-(wz + rz))), 1.0 / (1.0 + np.exp(-(wr + rr)))
        rn, bn = r[2 * hidden :], b[1, 2 * hidden :]
        inner = reset * (h @ rn.T + bn) if before else (reset * h) @ rn.T + bn
        n = np.tanh(wn + inner)
        return np.asarray((1.0 - z) * n + z * h)

    def step32(self, m: Matrices, x: np.ndarray, h: np.ndarray, before: bool) -> np.ndarray:
        """Bit for bit what the generated C (float32 or int8 weights) computes: the next h."""
        hidden = m.r.shape[1]
        zr_rows, n_rows = slice(0, 2 * hidden), slice(2 * hidden, 3 * hidden)

        def scale(v: np.ndarray | None, rows: slice) -> np.ndarray | None:
            return None if v is None else v[rows]

        zr = self.sums32(
            (m.b[0] + m.b[1])[zr_rows].astype(F),
            [(m.w[zr_rows], scale(m.w_scale, zr_rows), x), (m.r[zr_rows], scale(m.r_scale, zr_rows), h)],
        )
        z, reset = sigmoid_det(zr[:, :hidden]), sigmoid_det(zr[:, hidden:])
        wn = self.sums32(m.b[0, n_rows], [(m.w[n_rows], scale(m.w_scale, n_rows), x)])
        if before:
            rn = self.sums32(m.b[1, n_rows], [(m.r[n_rows], scale(m.r_scale, n_rows), h)])
            n = tanh_det((wn + (reset * rn).astype(F)).astype(F))
        else:
            rn = self.sums32(m.b[1, n_rows], [(m.r[n_rows], scale(m.r_scale, n_rows), (reset * h).astype(F))])
            n = tanh_det((wn + rn).astype(F))
        return np.asarray((((F(1.0) - z) * n).astype(F) + (z * h).astype(F)), F)

    def emit(self, node: Node, ctx: EmitContext, n: int) -> list[str]:
        constants = {k: ctx.constant(k) for k in node.inputs[W : B + 1] if k}
        m = self.matrices(node, constants, "int8" if ctx.quantize else "float32")  # type: ignore[arg-type]
        wc, rc, sw, sr = self._declare(node, ctx, m, "z, r, h")
        hidden = n
        bzr = (m.b[0] + m.b[1])[: 2 * hidden].astype(F)
        bc = ctx.const(
            f"{node.name}#B",
            np.concatenate([bzr, m.b[0, 2 * hidden :], m.b[1, 2 * hidden :]]),
            f"GRU '{node.name}' bias: z and r (input + recurrent), h input, h recurrent",
        )
        x, h = ctx.ref(node.inputs[X]), ctx.ref(node.inputs[INITIAL_H])
        sig, tanh = ctx.helper("sigmoid_det"), ctx.helper("tanh_det")
        features = ctx.size(node.inputs[X])
        before = int(node.attr("linear_before_reset", 0)) != 0
        gate_row, n_row = f"(g * {n}u) + j", f"{2 * hidden}u + j"
        gates = self.sum_c(
            "acc[g]",
            f"{bc}[{gate_row}]",
            [(wc, sw, f"{x}[k]", features), (rc, sr, f"{h}[k]", n)],
            gate_row,
            "gate",
        )
        wn = self.sum_c("wn", f"{bc}[{2 * hidden}u + j]", [(wc, sw, f"{x}[k]", features)], n_row, "wn")
        # The candidate's recurrent term sums over every unit's reset gate (linear_before_reset=0), so the
        # gates of all units come first.
        recurrent = f"{h}[k]" if before else f"(rg[k] * {h}[k])"
        rn = self.sum_c("rn", f"{bc}[{3 * hidden}u + j]", [(rc, sr, recurrent, n)], n_row, "rn")
        cand = f"{tanh}(wn + (rg[j] * rn))" if before else f"{tanh}(wn + rn)"
        return [
            "{",
            f"float zg[{n}];",
            f"float rg[{n}];",
            f"for (uint32_t j = 0u; j < {n}u; ++j) {{",
            "    float acc[2];",
            "    for (uint32_t g = 0u; g < 2u; ++g) {",
            *("        " + line for line in gates),
            "    }",
            f"    zg[j] = {sig}(acc[0]);",
            f"    rg[j] = {sig}(acc[1]);",
            "}",
            f"for (uint32_t j = 0u; j < {n}u; ++j) {{",
            "    float wn;",
            "    float rn;",
            *("    " + line for line in wn),
            *("    " + line for line in rn),
            f"    const float cand = {cand};",
            f"    const float h_next = ((1.0f - zg[j]) * cand) + (zg[j] * {h}[j]);",
            *self._outputs_c(node, ctx, ("h_next", "h_next")),
            "}",
            "}",
        ]
