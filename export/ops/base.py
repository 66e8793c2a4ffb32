"""What every op shares: the emitter interface, attribute and arity checks, and the reference hook.

Each op class owns its meaning in one place: ``check`` (validate everything, return the output shape),
``emit`` (the C; float32, or int8 weights when the context says so) and ``reference`` (NumPy, batched,
in a given precision). :mod:`embedrl.export.interpret` walks a graph once with the references, for
calibration (``float64``) and for the exact model of quantised C (``int8``).
"""

from __future__ import annotations

from collections.abc import Callable, Mapping, Sequence
from dataclasses import dataclass
from typing import ClassVar, Protocol

import numpy as np

from embedrl.export.errors import UnsupportedOpError
from embedrl.export.ir import AttrValue, Node

Shape = tuple[int, ...]
PRECISIONS = ("float64", "int8")
"""``float64``: the op's mathematical meaning (calibration); ``int8``: bit for bit what the generated
``--quantize int8`` C computes (float32 operations in the C's order, deterministic helpers)."""
F = np.float32
Interval = tuple[np.ndarray, np.ndarray]
"""Lower and upper bounds of every element of a value (float64)."""


@dataclass(frozen=True)
class Affine:
    """A matrix product with constant weights: ``y = alpha * (weights @ x) + beta * bias``."""

    weights: np.ndarray
    """float64, output-major [N, K]."""
    bias: np.ndarray | None
    """float64 [N] (a scalar bias broadcast), or None."""
    alpha: float = 1.0
    beta: float = 1.0


class EmitContext(Protocol):
    """What an emitter may ask of the code generator."""

    prefix: str
    """The policy's name: the prefix of every generated symbol."""

    quantize: str | None
    """None for float32 code, "int8" for int8 weights (see export.quantize)."""
    rows: str | None
    """None for one observation; for a block of observations, the C expression of its row count: then
    :meth:`ref` of a runtime value names row ``r`` of its block buffer, and an emitter that is not
    :attr:`Emitter.batched` has its statements run once per row."""

    def helper(self, name: str) -> str:
        """Emit the named deterministic math helper (``exp_det``, ``tanh_det``, ``sigmoid_det``) once."""
        ...

    def function(self, name: str, source: Callable[[str], str]) -> str:
        """Emit the static C function ``{prefix}_{name}`` once (``source(prefix)`` is its definition) and
        return its symbol."""
        ...

    def ref(self, value: str) -> str:
        """C expression for the array holding ``value`` (a buffer, the input, or a constant)."""
        ...

    def const(self, key: str, array: np.ndarray, comment: str, condition: str = "") -> str:
        """Declare a ``static const`` float (or integer) array, 1-D or 2-D, once and return its symbol;
        with a ``condition`` (a preprocessor expression), the array is compiled only where it holds."""
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
    max_outputs = 1
    """More than one for ops with several results (a recurrent cell's output and next state); the first is
    required, later ones may be omitted (empty names)."""
    alias = False
    """True if the output is the input's data unchanged (no code, same storage)."""
    in_place = False
    """True if the output may overwrite its first runtime input's storage (element-wise)."""
    batched: ClassVar[bool] = False
    """True if :meth:`emit` writes its own loop over a block's rows (``ctx.rows``): a matrix product reads
    each weight once per block; otherwise the generator runs the op's statements once per row."""

    def check(self, node: Node, shapes: Mapping[str, Shape], constants: Mapping[str, np.ndarray]) -> Shape:
        unknown = sorted(set(node.attrs) - set(self.attrs))
        if unknown:
            raise _fail(
                node, f"unsupported attribute(s) {unknown}; supported: {sorted(self.attrs) or 'none'}"
            )
        present = [i for i in node.inputs if i != ""]
        outputs = len(node.outputs)
        if (
            not self.min_inputs <= len(present) <= self.max_inputs
            or not 1 <= outputs <= self.max_outputs
            or not node.outputs[0]
        ):
            raise _fail(
                node,
                f"takes {self.min_inputs}..{self.max_inputs} inputs and 1..{self.max_outputs} output(s), "
                f"got {len(present)} and {outputs}",
            )
        if node.inputs[0] in constants:
            raise _fail(node, "the first input must be a runtime value, not a constant")
        return self.shape(node, shapes, constants)

    def shape(self, node: Node, shapes: Mapping[str, Shape], constants: Mapping[str, np.ndarray]) -> Shape:
        return shapes[node.inputs[0]]

    def output_shapes(self, node: Node, first: Shape) -> tuple[Shape, ...]:
        """The shape of every output, given the first's from :meth:`check` (ops with one output: just it)."""
        return (first,)

    quantizable: ClassVar[bool] = True
    """Whether ``--quantize int8`` code and its ``int8`` reference exist for this op."""
    monotone: ClassVar[bool] = False
    """Whether each output element is monotone in its runtime input for fixed constant operands (then its
    interval is spanned by the reference at the input interval's two ends); otherwise :meth:`bounds` gives
    up unless the op overrides it."""
    bounded_by_itself: ClassVar[bool] = False
    """Whether :meth:`bounds` holds whatever the other runtime operands are (a recurrent cell's hidden
    state is within [-1, 1] for any state it reads)."""
    linear: ClassVar[bool] = False
    commutative: ClassVar[bool] = False
    """Whether the two operands may swap (the importer puts a constant first operand second)."""
    q15_float: ClassVar[frozenset[str]] = frozenset()
    """Where the op may run in float32 around a q15 section: "before" (input normalisation), "after"
    (action post-processing)."""
    """A matrix product with constant weights, described by :meth:`affine` (q15 layers, interval bounds)."""

    def affine(self, node: Node, constants: Mapping[str, np.ndarray]) -> Affine:
        """The op as weights, bias and scales (linear ops only)."""
        raise _fail(node, "is not a matrix product")

    def bounds(self, node: Node, x: Interval, constants: Mapping[str, np.ndarray], size: int) -> Interval:
        """Bounds of the output (``size`` elements) for a runtime input within ``x`` and constant other
        operands: monotone ops from their reference at both ends, others unbounded (the safe answer)."""
        if not self.monotone:
            return np.full(size, -np.inf), np.full(size, np.inf)
        operands = [constants[i].astype(np.float64).reshape(-1) for i in node.inputs[1:] if i]
        ends = [
            self.reference(node, [end.reshape(1, -1), *operands], constants, "float64").reshape(-1)
            for end in x
        ]
        return np.minimum(*ends), np.maximum(*ends)

    def later_bounds(self, node: Node, first: Interval, sizes: Sequence[int]) -> list[Interval]:
        """Bounds of the outputs after the first (of ``sizes`` elements; 0 for an omitted one), given the
        first's: unbounded."""
        return [(np.full(n, -np.inf), np.full(n, np.inf)) for n in sizes]

    def emit(self, node: Node, ctx: EmitContext, n: int) -> list[str]:
        """C statements computing ``node.outputs`` (the first has ``n`` elements)."""
        raise NotImplementedError

    def reference(
        self, node: Node, inputs: Sequence[np.ndarray], constants: Mapping[str, np.ndarray], precision: str
    ) -> np.ndarray:
        """The output for a batch: ``inputs[0]`` is [B, n] (runtime), later inputs are runtime [B, m] or
        flattened constants; ``precision`` is one of :data:`PRECISIONS`. An op with several outputs returns
        them stacked on a leading axis ([outputs, B, n], all of one size)."""
        raise UnsupportedOpError(f"{node.op} node '{node.name}' has no {precision} reference")
