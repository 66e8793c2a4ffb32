"""One emitter per ONNX op, registered in :data:`EMITTERS`.

Each emitter has ``check(node, shapes, constants)``, which validates everything (input count,
which inputs must be constants, ranks, every attribute: unknown attributes are errors) and
returns the output shape, and ``emit(node, ctx)``, which returns C statements and cannot fail.

Shapes are static; the batch dimension is 1. Element-wise ops accept a second operand that
has the same number of elements as the output or a single element.
"""

from __future__ import annotations

from collections.abc import Mapping
from typing import ClassVar, Protocol

import numpy as np

from embedrl.export.errors import UnsupportedOpError
from embedrl.export.ir import AttrValue, Node

Shape = tuple[int, ...]


class EmitContext(Protocol):
    """What an emitter may ask of the code generator."""

    quantize: str | None
    """None for float32 code, "int8" for int8 weights (see export.quantize)."""

    def helper(self, name: str) -> str:
        """Emit the named deterministic math helper (``exp_det``, ``tanh_det``, ``sigmoid_det``) once."""
        ...

    def ref(self, value: str) -> str:
        """C expression for the array holding ``value`` (a buffer, the input, or a constant)."""
        ...

    def const(self, key: str, array: np.ndarray, comment: str) -> str:
        """Declare a ``static const`` float (or int8) array, 1-D or 2-D, once and return its symbol."""
        ...

    def literal(self, value: float) -> str:
        """A C float literal that round-trips ``value`` exactly."""
        ...

    def constant(self, value: str) -> np.ndarray | None:
        """The array of a constant value, or None for a runtime value."""
        ...

    def size(self, value: str) -> int:
        """Number of elements of a value."""
        ...


def _size(shape: Shape) -> int:
    return int(np.prod(shape, dtype=np.int64))


def _fail(node: Node, what: str) -> UnsupportedOpError:
    return UnsupportedOpError(f"{node.op} node '{node.name}': {what}")


class Emitter:
    """Base class: attribute and arity validation shared by every op."""

    attrs: ClassVar[Mapping[str, AttrValue]] = {}
    """Supported attributes and their defaults; anything else is rejected."""
    min_inputs = 1
    max_inputs = 1
    alias = False
    """True if the output is the input's data unchanged (no code, same storage)."""
    in_place = False
    """True if the output may overwrite its first runtime input's storage (element-wise)."""

    def check(self, node: Node, shapes: Mapping[str, Shape], constants: Mapping[str, np.ndarray]) -> Shape:
        unknown = sorted(set(node.attrs) - set(self.attrs))
        if unknown:
            raise _fail(
                node, f"unsupported attribute(s) {unknown}; supported: {sorted(self.attrs) or 'none'}"
            )
        present = [i for i in node.inputs if i != ""]
        if not self.min_inputs <= len(present) <= self.max_inputs or len(node.outputs) != 1:
            raise _fail(
                node,
                f"takes {self.min_inputs}..{self.max_inputs} inputs and 1 output, "
                f"got {len(present)} and {len(node.outputs)}",
            )
        if node.inputs[0] in constants:
            raise _fail(node, "the first input must be a runtime value, not a constant")
        return self.shape(node, shapes, constants)

    def shape(self, node: Node, shapes: Mapping[str, Shape], constants: Mapping[str, np.ndarray]) -> Shape:
        return shapes[node.inputs[0]]

    def emit(self, node: Node, ctx: EmitContext, n: int) -> list[str]:
        """C statements computing ``node.outputs[0]`` (``n`` elements)."""
        raise NotImplementedError


# -- element-wise unary ------------------------------------------------------------------------


class Unary(Emitter):
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
        return [f"for (int i = 0; i < {n}; ++i) {{", f"    {y}[i] = {expr};", "}"]

    def formats(self, node: Node, ctx: EmitContext) -> dict[str, str]:
        return {}


class Relu(Unary):
    expression = "{x} > 0.0f ? {x} : 0.0f"


class LeakyRelu(Unary):
    attrs: ClassVar[Mapping[str, AttrValue]] = {"alpha": 0.01}
    expression = "{x} >= 0.0f ? {x} : {alpha} * {x}"

    def formats(self, node: Node, ctx: EmitContext) -> dict[str, str]:
        return {"alpha": ctx.literal(float(node.attr("alpha", 0.01)))}


class Tanh(Unary):
    expression = "tanhf({x})"
    helper = "tanh_det"


class Sigmoid(Unary):
    expression = "1.0f / (1.0f + expf(-{x}))"
    helper = "sigmoid_det"


class Softplus(Unary):
    # log(1 + e^x) without overflow: x + log1p(e^-x) for x > 0.
    expression = "{x} > 0.0f ? {x} + log1pf(expf(-{x})) : log1pf(expf({x}))"


class Clip(Unary):
    """Clip with optional constant scalar ``min`` and ``max`` inputs (opset >= 11)."""

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
        lines = [f"for (int i = 0; i < {n}; ++i) {{", f"    float v = {x}[i];"]
        names = ("min", "max")
        for k, bound in enumerate(node.inputs[1:3]):
            array = ctx.constant(bound) if bound else None
            if array is None:
                continue
            lit = ctx.literal(float(array.reshape(-1)[0]))
            op = "<" if names[k] == "min" else ">"
            lines.append(f"    v = v {op} {lit} ? {lit} : v;")
        lines += [f"    {y}[i] = v;", "}"]
        return lines


class Identity(Emitter):
    alias = True

    def emit(self, node: Node, ctx: EmitContext, n: int) -> list[str]:
        return []


# -- element-wise binary -----------------------------------------------------------------------


class Binary(Emitter):
    min_inputs = max_inputs = 2
    in_place = True
    operator = "+"
    function = ""
    """If set, a C function of two floats (e.g. ``fmaxf``) instead of an infix operator."""

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
        expr = f"{self.function}({a}, {b})" if self.function else f"{a} {self.operator} {b}"
        return [f"for (int i = 0; i < {n}; ++i) {{", f"    {y}[i] = {expr};", "}"]


class Add(Binary):
    operator = "+"


class Sub(Binary):
    operator = "-"


class Mul(Binary):
    operator = "*"


class Div(Binary):
    operator = "/"


class Max(Binary):
    function = "fmaxf"


class Min(Binary):
    function = "fminf"


# -- matrix products ---------------------------------------------------------------------------


def _input_major(node: Node, b: np.ndarray, transposed: bool) -> np.ndarray:
    """Weights as ``W[k][n]`` (input-major): the inner loop runs over outputs and vectorises."""
    return np.ascontiguousarray(b.T if transposed else b, dtype=np.float32)


K_BLOCK = 4
"""Inputs folded into one pass over the outputs: fewer loads and stores of the accumulator row."""


def _matmul_lines(x: str, y: str, w: str, k: int, n: int, init: str, cast: str = "") -> list[str]:
    # Per output the sum runs in a fixed order (init, then k = 0, 1, ...): the blocked pass
    # y[n] = y[n] + x0*w0[n] + x1*w1[n] + ... evaluates left to right, and vectorising over n
    # never reassociates it, so the result does not depend on the optimisation level.
    lines = [f"for (int n = 0; n < {n}; ++n) {{", f"    {y}[n] = {init};", "}"]
    full = k - k % K_BLOCK
    if full:
        terms = " + ".join(f"x{j} * {cast}{w}[k + {j}][n]" for j in range(K_BLOCK))
        lines += [
            f"for (int k = 0; k < {full}; k += {K_BLOCK}) {{",
            *[f"    const float x{j} = {x}[k + {j}];" for j in range(K_BLOCK)],
            f"    for (int n = 0; n < {n}; ++n) {{",
            f"        {y}[n] = {y}[n] + {terms};",
            "    }",
            "}",
        ]
    for k0 in range(full, k):
        lines += [
            f"for (int n = 0; n < {n}; ++n) {{",
            f"    {y}[n] = {y}[n] + {x}[{k0}] * {cast}{w}[{k0}][n];",
            "}",
        ]
    return lines


def _quantized_lines(
    node: Node, ctx: EmitContext, w: np.ndarray, bias: str | None, x: str, y: str, n: int
) -> list[str]:
    """int8 weights per output channel: acc = sum x[k] * q[k][n]; y[n] = b[n] + s[n] * acc[n]."""
    from embedrl.export.quantize import quantize_columns

    q, scale = quantize_columns(w)
    k = w.shape[0]
    qsym = ctx.const(node.inputs[1] + "#int8", q, f"{node.name} weights, int8, input-major [{k}][{n}]")
    ssym = ctx.const(node.inputs[1] + "#scale", scale, f"{node.name} per-output scales [{n}]")
    lines = _matmul_lines(x, y, qsym, k, n, "0.0f", cast="(float)")
    scaled = f"{ssym}[n] * {y}[n]"
    return [
        *lines,
        f"for (int n = 0; n < {n}; ++n) {{",
        f"    {y}[n] = {bias + ' + ' if bias else ''}{scaled};",
        "}",
    ]


class Gemm(Emitter):
    """``Y = alpha * A @ op(B) + beta * C`` with A a runtime [1, K] row and B, C constants."""

    attrs: ClassVar[Mapping[str, AttrValue]] = {"alpha": 1.0, "beta": 1.0, "transA": 0, "transB": 0}
    min_inputs, max_inputs = 2, 3

    def shape(self, node: Node, shapes: Mapping[str, Shape], constants: Mapping[str, np.ndarray]) -> Shape:
        if int(node.attr("transA", 0)) != 0:
            raise _fail(node, "transA=1 is not supported (A is the observation row)")
        if int(node.attr("transB", 0)) not in (0, 1):
            raise _fail(node, f"transB must be 0 or 1, got {node.attr('transB', 0)}")
        a = shapes[node.inputs[0]]
        if len(a) != 2 or a[0] != 1:
            raise _fail(node, f"A must have shape [1, K], got {list(a)}")
        b_name = node.inputs[1]
        if b_name not in constants:
            raise _fail(node, f"B '{b_name}' must be a constant (weights as initializers)")
        b = constants[b_name]
        if b.ndim != 2:
            raise _fail(node, f"B must be 2-D, got shape {list(b.shape)}")
        k, n = (b.shape[1], b.shape[0]) if int(node.attr("transB", 0)) else b.shape
        if k != a[1]:
            raise _fail(node, f"A has {a[1]} columns but op(B) has {k} rows")
        if len(node.inputs) > 2 and node.inputs[2] != "":
            c_name = node.inputs[2]
            if c_name not in constants:
                raise _fail(node, f"C '{c_name}' must be a constant (bias as initializer)")
            if constants[c_name].size not in (1, n):
                raise _fail(node, f"C must have 1 or {n} elements, got shape {list(constants[c_name].shape)}")
        return (1, int(n))

    def emit(self, node: Node, ctx: EmitContext, n: int) -> list[str]:
        b = ctx.constant(node.inputs[1])
        assert b is not None
        w = _input_major(node, b, bool(node.attr("transB", 0)))
        k = w.shape[0]
        wsym = (
            ""
            if ctx.quantize
            else ctx.const(node.inputs[1] + "#input-major", w, f"{node.name} weights, input-major [{k}][{n}]")
        )
        alpha, beta = float(node.attr("alpha", 1.0)), float(node.attr("beta", 1.0))
        c = ctx.constant(node.inputs[2]) if len(node.inputs) > 2 and node.inputs[2] else None
        x, y = ctx.ref(node.inputs[0]), ctx.ref(node.outputs[0])
        if c is None:
            bias = None
        elif c.size == 1:
            bias = ctx.literal(float(c.reshape(-1)[0]))
        else:
            bias = f"{ctx.const(node.inputs[2], c.reshape(-1), f'{node.name} bias [{n}]')}[n]"
        if ctx.quantize:
            return _quantized_lines(node, ctx, w, bias, x, y, n)
        if alpha == 1.0 and beta == 1.0:
            return _matmul_lines(x, y, wsym, k, n, bias or "0.0f")
        lines = _matmul_lines(x, y, wsym, k, n, "0.0f")
        scaled = f"{ctx.literal(alpha)} * {y}[n]"
        if bias is not None:
            scaled += f" + {ctx.literal(beta)} * {bias}"
        return [*lines, f"for (int n = 0; n < {n}; ++n) {{", f"    {y}[n] = {scaled};", "}"]


class MatMul(Emitter):
    """``Y = A @ B`` with A a runtime [1, K] row (or [K] vector) and B a constant [K, N]."""

    min_inputs = max_inputs = 2

    def shape(self, node: Node, shapes: Mapping[str, Shape], constants: Mapping[str, np.ndarray]) -> Shape:
        a = shapes[node.inputs[0]]
        if not (len(a) == 1 or (len(a) == 2 and a[0] == 1)):
            raise _fail(node, f"A must have shape [K] or [1, K], got {list(a)}")
        if node.inputs[1] not in constants:
            raise _fail(node, f"B '{node.inputs[1]}' must be a constant (weights as initializers)")
        b = constants[node.inputs[1]]
        if b.ndim != 2 or b.shape[0] != a[-1]:
            raise _fail(node, f"B must have shape [{a[-1]}, N], got {list(b.shape)}")
        return (*a[:-1], int(b.shape[1]))

    def emit(self, node: Node, ctx: EmitContext, n: int) -> list[str]:
        b = ctx.constant(node.inputs[1])
        assert b is not None
        w = _input_major(node, b, False)
        x, y = ctx.ref(node.inputs[0]), ctx.ref(node.outputs[0])
        if ctx.quantize:
            return _quantized_lines(node, ctx, w, None, x, y, n)
        wsym = ctx.const(node.inputs[1] + "#input-major", w, f"{node.name} weights [{w.shape[0]}][{n}]")
        return _matmul_lines(x, y, wsym, w.shape[0], n, "0.0f")


# -- shape ops (no code: the output aliases the input) -----------------------------------------


class Flatten(Emitter):
    attrs: ClassVar[Mapping[str, AttrValue]] = {"axis": 1}
    alias = True

    def shape(self, node: Node, shapes: Mapping[str, Shape], constants: Mapping[str, np.ndarray]) -> Shape:
        shape = shapes[node.inputs[0]]
        axis = int(node.attr("axis", 1))
        if not -len(shape) <= axis <= len(shape):
            raise _fail(node, f"axis {axis} out of range for rank {len(shape)}")
        if axis < 0:
            axis += len(shape)
        return (_size(shape[:axis]), _size(shape[axis:]))

    def emit(self, node: Node, ctx: EmitContext, n: int) -> list[str]:
        return []


class Reshape(Emitter):
    attrs: ClassVar[Mapping[str, AttrValue]] = {"allowzero": 0}
    min_inputs = max_inputs = 2
    alias = True

    def shape(self, node: Node, shapes: Mapping[str, Shape], constants: Mapping[str, np.ndarray]) -> Shape:
        if int(node.attr("allowzero", 0)) != 0:
            raise _fail(node, "allowzero=1 is not supported")
        if node.inputs[1] not in constants:
            raise _fail(node, f"shape '{node.inputs[1]}' must be a constant (static shapes only)")
        source = shapes[node.inputs[0]]
        target = [int(d) for d in constants[node.inputs[1]].reshape(-1)]
        target = [source[i] if d == 0 else d for i, d in enumerate(target)]
        if target.count(-1) > 1 or any(d < -1 for d in target):
            raise _fail(node, f"invalid target shape {target}")
        if -1 in target:
            rest = _size(tuple(d for d in target if d != -1))
            if rest == 0 or _size(source) % rest:
                raise _fail(node, f"cannot reshape {list(source)} to {target}")
            target[target.index(-1)] = _size(source) // rest
        if _size(tuple(target)) != _size(source):
            raise _fail(node, f"cannot reshape {list(source)} to {target}")
        return tuple(target)

    def emit(self, node: Node, ctx: EmitContext, n: int) -> list[str]:
        return []


class Constant(Emitter):
    """Handled by the importer: its value becomes a graph constant; no code."""

    attrs: ClassVar[Mapping[str, AttrValue]] = {"value": 0}
    min_inputs = max_inputs = 0

    def check(self, node: Node, shapes: Mapping[str, Shape], constants: Mapping[str, np.ndarray]) -> Shape:
        return constants[node.outputs[0]].shape

    def emit(self, node: Node, ctx: EmitContext, n: int) -> list[str]:
        return []


EMITTERS: dict[str, Emitter] = {
    "Gemm": Gemm(),
    "MatMul": MatMul(),
    "Add": Add(),
    "Sub": Sub(),
    "Mul": Mul(),
    "Div": Div(),
    "Max": Max(),
    "Min": Min(),
    "Relu": Relu(),
    "LeakyRelu": LeakyRelu(),
    "Tanh": Tanh(),
    "Sigmoid": Sigmoid(),
    "Softplus": Softplus(),
    "Clip": Clip(),
    "Identity": Identity(),
    "Flatten": Flatten(),
    "Reshape": Reshape(),
    "Constant": Constant(),
}
"""The supported ops: the only place an op is registered."""
