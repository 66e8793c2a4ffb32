"""Element-wise ops: one value in, one out (Relu, LeakyRelu, Tanh, Sigmoid, Softplus, Clip), and two
values in (Add, Sub, Mul, Div, Max, Min; the second operand has the output's size or one element).

Every op keeps ONNX's NaN semantics: a NaN operand gives a NaN result (Relu, Clip, Max and Min included), so a
NaN anywhere in the network reaches the step's final finite check and becomes the safe action. A comparison
with NaN is false, so each C expression is written with the NaN case on the branch a false comparison takes.
"""

from __future__ import annotations

from collections.abc import Mapping, Sequence
from typing import ClassVar

import numpy as np

from embedrl.export.ir import AttrValue, Node
from embedrl.export.ops.base import EmitContext, Emitter, F, Shape, _fail, _size
from embedrl.export.ops.deterministic import sigmoid_det, tanh_det


class Unary(Emitter):
    monotone = True  # every unary op here is increasing (Clip, Relu, ...) in its input
    in_place = True
    expression = "{x}"
    """C expression of one element ``{x}``; ``{alpha}`` etc. come from attributes."""
    helper = ""
    """Deterministic helper used instead of ``expression`` in quantised code (libm's tanhf and expf
    differ between C libraries, and quantised policies must equal their Python model bit for bit)."""

    def emit(self, node: Node, ctx: EmitContext, n: int) -> list[str]:
        x, y = ctx.ref(node.inputs[0]), ctx.ref(node.outputs[0])
        if ctx.quantize and self.helper:
            expr = f"{ctx.helper(self.helper)}({x}[i])"
        else:
            expr = self.expression.format(x=f"{x}[i]", **self.formats(node, ctx))
        return [f"for (uint32_t i = 0u; i < {n}u; ++i) {{", f"    {y}[i] = {expr};", "}"]

    def formats(self, node: Node, ctx: EmitContext) -> dict[str, str]:
        return {}

    def reference(
        self, node: Node, inputs: Sequence[np.ndarray], constants: Mapping[str, np.ndarray], precision: str
    ) -> np.ndarray:
        x = inputs[0]
        return self.exact(node, x) if precision == "float64" else self.float32(node, x).astype(F)

    def exact(self, node: Node, x: np.ndarray) -> np.ndarray:
        """The op's meaning in float64."""
        raise NotImplementedError

    def float32(self, node: Node, x: np.ndarray) -> np.ndarray:
        """What the quantised C computes, in float32 operations."""
        raise NotImplementedError


class Relu(Unary):
    q15_float = frozenset({"after"})  # action post-processing after a q15 section
    expression = "({x} < 0.0f) ? 0.0f : {x}"  # NaN < 0 is false: NaN stays NaN

    def exact(self, node: Node, x: np.ndarray) -> np.ndarray:
        return np.asarray(np.maximum(x, 0))

    def float32(self, node: Node, x: np.ndarray) -> np.ndarray:
        return np.where(x < 0, F(0.0), x)


class LeakyRelu(Unary):
    attrs: ClassVar[Mapping[str, AttrValue]] = {"alpha": 0.01}
    expression = "({x} >= 0.0f) ? {x} : ({alpha} * {x})"

    def formats(self, node: Node, ctx: EmitContext) -> dict[str, str]:
        return {"alpha": ctx.literal(float(node.attr("alpha", 0.01)))}

    def exact(self, node: Node, x: np.ndarray) -> np.ndarray:
        return np.where(x >= 0, x, float(node.attr("alpha", 0.01)) * x)

    def float32(self, node: Node, x: np.ndarray) -> np.ndarray:
        return np.where(x >= 0, x, (F(node.attr("alpha", 0.01)) * x).astype(F))


class Tanh(Unary):
    q15_float = frozenset({"after"})  # action post-processing after a q15 section
    expression = "tanhf({x})"
    helper = "tanh_det"

    def exact(self, node: Node, x: np.ndarray) -> np.ndarray:
        return np.asarray(np.tanh(x))

    def float32(self, node: Node, x: np.ndarray) -> np.ndarray:
        return tanh_det(x)


class Sigmoid(Unary):
    q15_float = frozenset({"after"})  # action post-processing after a q15 section
    expression = "1.0f / (1.0f + expf(-{x}))"
    helper = "sigmoid_det"

    def exact(self, node: Node, x: np.ndarray) -> np.ndarray:
        return np.asarray(1 / (1 + np.exp(-x)))

    def float32(self, node: Node, x: np.ndarray) -> np.ndarray:
        return sigmoid_det(x)


class Softplus(Unary):
    # log(1 + e^x) without overflow: x + log1p(e^-x) for x > 0.
    expression = "{x} > 0.0f ? {x} + log1pf(expf(-{x})) : log1pf(expf({x}))"
    quantizable = False  # no deterministic log1p helper: quantised code would depend on libm

    def exact(self, node: Node, x: np.ndarray) -> np.ndarray:
        return np.asarray(np.logaddexp(0.0, x))


class Clip(Unary):
    """Clip with optional constant scalar ``min`` and ``max`` inputs (opset >= 11)."""

    q15_float = frozenset({"before", "after"})  # normalisation and post-processing around q15

    max_inputs = 3

    def shape(self, node: Node, shapes: Mapping[str, Shape], constants: Mapping[str, np.ndarray]) -> Shape:
        for bound in node.inputs[1:]:
            if bound == "":
                continue
            if bound not in constants:
                raise _fail(node, f"bound '{bound}' must be a constant")
            if constants[bound].size != 1:
                raise _fail(node, f"bound '{bound}' must be a scalar, got shape {constants[bound].shape}")
            if not np.isfinite(constants[bound]).all():
                raise _fail(node, f"bound '{bound}' must be finite")
        return shapes[node.inputs[0]]

    def emit(self, node: Node, ctx: EmitContext, n: int) -> list[str]:
        x, y = ctx.ref(node.inputs[0]), ctx.ref(node.outputs[0])
        lines = [f"for (uint32_t i = 0u; i < {n}u; ++i) {{", f"    float v = {x}[i];"]
        names = ("min", "max")
        for k, bound in enumerate(node.inputs[1:3]):
            array = ctx.constant(bound) if bound else None
            if array is None:
                continue
            lit = ctx.literal(float(array.reshape(-1)[0]))
            op = "<" if names[k] == "min" else ">"
            lines.append(f"    v = (v {op} {lit}) ? {lit} : v;")
        lines += [f"    {y}[i] = v;", "}"]
        return lines

    def reference(
        self, node: Node, inputs: Sequence[np.ndarray], constants: Mapping[str, np.ndarray], precision: str
    ) -> np.ndarray:
        y = inputs[0].copy()
        dtype = np.float64 if precision == "float64" else F
        for k, bound in enumerate(node.inputs[1:3]):
            if bound:
                v = dtype(constants[bound].reshape(-1)[0])
                y = np.where(y < v, v, y) if k == 0 else np.where(y > v, v, y)
        return y.astype(dtype)


class Binary(Emitter):
    monotone = True  # with one operand constant: increasing, or decreasing for a negative factor/divisor
    q15_float = frozenset({"before", "after"})  # normalisation and post-processing around q15
    min_inputs = max_inputs = 2
    in_place = True
    operator = "+"
    select = ""
    """If set, a C expression of ``{a}`` and ``{b}`` instead of ``a operator b`` (Max, Min)."""

    def shape(self, node: Node, shapes: Mapping[str, Shape], constants: Mapping[str, np.ndarray]) -> Shape:
        a, b = (shapes[i] for i in node.inputs)
        try:
            out = tuple(int(d) for d in np.broadcast_shapes(a, b))
        except ValueError:
            raise _fail(node, f"shapes {a} and {b} do not broadcast") from None
        if _size(out) != _size(a):
            raise _fail(node, f"broadcasting {a} with {b} would grow the first operand to {out}")
        if _size(b) not in (1, _size(out)):
            raise _fail(node, f"second operand of shape {b} must have 1 or {_size(out)} elements")
        return out

    def emit(self, node: Node, ctx: EmitContext, n: int) -> list[str]:
        y = ctx.ref(node.outputs[0])
        a = f"{ctx.ref(node.inputs[0])}[i]"
        b_const = ctx.constant(node.inputs[1])
        if b_const is not None and b_const.size == 1:
            b = ctx.literal(float(b_const.reshape(-1)[0]))
        elif b_const is not None:
            b = f"{ctx.const(node.inputs[1], b_const.reshape(-1), f'{node.name} operand [{n}]')}[i]"
        else:
            ref = ctx.ref(node.inputs[1])
            b = f"{ref}[0]" if ctx.size(node.inputs[1]) == 1 else f"{ref}[i]"
        expr = self.select.format(a=a, b=b) if self.select else f"{a} {self.operator} {b}"
        return [f"for (uint32_t i = 0u; i < {n}u; ++i) {{", f"    {y}[i] = {expr};", "}"]

    @staticmethod
    def numpy(a: np.ndarray, b: np.ndarray) -> np.ndarray:
        """The C expression's meaning, element by element (NumPy broadcasting)."""
        raise NotImplementedError

    def reference(
        self, node: Node, inputs: Sequence[np.ndarray], constants: Mapping[str, np.ndarray], precision: str
    ) -> np.ndarray:
        x, b = inputs[0], inputs[1]
        if precision == "float64":
            return np.asarray(self.numpy(x, b), np.float64)
        operand = b[0] if b.size == 1 else b.reshape(1, -1) if b.ndim == 1 else b
        return np.asarray(self.numpy(x, operand)).astype(F)


class Add(Binary):
    commutative = True
    operator = "+"

    @staticmethod
    def numpy(a: np.ndarray, b: np.ndarray) -> np.ndarray:
        return np.asarray(np.add(a, b))


class Sub(Binary):
    operator = "-"

    @staticmethod
    def numpy(a: np.ndarray, b: np.ndarray) -> np.ndarray:
        return np.asarray(np.subtract(a, b))


class Mul(Binary):
    commutative = True
    operator = "*"

    @staticmethod
    def numpy(a: np.ndarray, b: np.ndarray) -> np.ndarray:
        return np.asarray(np.multiply(a, b))


class Div(Binary):
    operator = "/"

    @staticmethod
    def numpy(a: np.ndarray, b: np.ndarray) -> np.ndarray:
        return np.asarray(np.divide(a, b))


class Max(Binary):
    commutative = True
    # Both comparisons are false only when an operand is NaN; then a + b is NaN (fmaxf would drop it).
    select = "{a} < {b} ? {b} : ({a} >= {b} ? {a} : {a} + {b})"

    @staticmethod
    def numpy(a: np.ndarray, b: np.ndarray) -> np.ndarray:
        return np.where(a < b, b, np.where(a >= b, a, a + b))


class Min(Binary):
    commutative = True
    select = "{a} > {b} ? {b} : ({a} <= {b} ? {a} : {a} + {b})"

    @staticmethod
    def numpy(a: np.ndarray, b: np.ndarray) -> np.ndarray:
        return np.where(a > b, b, np.where(a <= b, a, a + b))
