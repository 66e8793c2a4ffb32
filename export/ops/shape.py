"""Shape ops: Identity, Flatten, Reshape, Squeeze, Unsqueeze and Gather of a size-1 axis (the output is the
input's data: no code) and Constant
(its value becomes a graph constant when the model is imported)."""

from __future__ import annotations

from collections.abc import Mapping, Sequence
from typing import ClassVar

import numpy as np

from embedrl.export.ir import AttrValue, Node
from embedrl.export.ops.base import EmitContext, Emitter, Shape, _fail, _size


class Alias(Emitter):
    monotone = True  # the same data
    q15_float = frozenset({"before", "after"})  # normalisation and post-processing around q15
    """An op whose output is its input's data: no code, and the reference passes the values on."""

    alias = True

    def emit(self, node: Node, ctx: EmitContext, n: int) -> list[str]:
        return []

    def reference(
        self, node: Node, inputs: Sequence[np.ndarray], constants: Mapping[str, np.ndarray], precision: str
    ) -> np.ndarray:
        return inputs[0]


class Identity(Alias):
    """The value unchanged."""


class Flatten(Alias):
    attrs: ClassVar[Mapping[str, AttrValue]] = {"axis": 1}

    def shape(self, node: Node, shapes: Mapping[str, Shape], constants: Mapping[str, np.ndarray]) -> Shape:
        shape = shapes[node.inputs[0]]
        axis = int(node.attr("axis", 1))
        if not -len(shape) <= axis <= len(shape):
            raise _fail(node, f"axis {axis} out of range for rank {len(shape)}")
        if axis < 0:
            axis += len(shape)
        return (_size(shape[:axis]), _size(shape[axis:]))


class Reshape(Alias):
    attrs: ClassVar[Mapping[str, AttrValue]] = {"allowzero": 0}
    min_inputs = max_inputs = 2

    def shape(self, node: Node, shapes: Mapping[str, Shape], constants: Mapping[str, np.ndarray]) -> Shape:
        if int(node.attr("allowzero", 0)) != 0:
            raise _fail(node, "allowzero=1 is not supported")
        if node.inputs[1] not in constants:
            raise _fail(node, f"shape '{node.inputs[1]}' must be a constant (static shapes only)")
        source = shapes[node.inputs[0]]
        target = [int(d) for d in constants[node.inputs[1]].reshape(-1)]
        if any(d == 0 and i >= len(source) for i, d in enumerate(target)):
            raise _fail(node, f"cannot reshape {list(source)} to {target}: a 0 copies an input dimension")
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


class _Axes(Alias):
    """Squeeze and Unsqueeze: the axes as a constant second input (opset 13)."""

    min_inputs = 1
    max_inputs = 2

    def axes(self, node: Node, constants: Mapping[str, np.ndarray], rank: int) -> list[int]:
        if len(node.inputs) < 2 or not node.inputs[1]:
            return []
        if node.inputs[1] not in constants:
            raise _fail(node, f"axes '{node.inputs[1]}' must be a constant (static shapes only)")
        axes = [int(a) for a in constants[node.inputs[1]].reshape(-1)]
        if any(not -rank <= a < rank for a in axes) or len({a % rank for a in axes}) != len(axes):
            raise _fail(node, f"axes {axes} out of range or repeated for rank {rank}")
        return sorted(a % rank for a in axes)


class Squeeze(_Axes):
    """Drops size-1 axes (all of them without ``axes``)."""

    def shape(self, node: Node, shapes: Mapping[str, Shape], constants: Mapping[str, np.ndarray]) -> Shape:
        source = shapes[node.inputs[0]]
        axes = self.axes(node, constants, len(source)) or [i for i, d in enumerate(source) if d == 1]
        if any(source[a] != 1 for a in axes):
            raise _fail(node, f"cannot squeeze axes {axes} of shape {list(source)}: not of size 1")
        return tuple(d for i, d in enumerate(source) if i not in axes)


class Unsqueeze(_Axes):
    """Inserts size-1 axes."""

    min_inputs = 2

    def shape(self, node: Node, shapes: Mapping[str, Shape], constants: Mapping[str, np.ndarray]) -> Shape:
        source = list(shapes[node.inputs[0]])
        for a in self.axes(
            node, constants, len(source) + len(constants.get(node.inputs[1], np.zeros(0)).reshape(-1))
        ):
            source.insert(a, 1)
        return tuple(source)


class Gather(Alias):
    """Gather with a constant scalar index into an axis of size 1 (``y[0]`` of a one-step sequence): the
    axis dropped, the same data."""

    attrs: ClassVar[Mapping[str, AttrValue]] = {"axis": 0}
    min_inputs = max_inputs = 2

    def shape(self, node: Node, shapes: Mapping[str, Shape], constants: Mapping[str, np.ndarray]) -> Shape:
        source = shapes[node.inputs[0]]
        axis = int(node.attr("axis", 0))
        if not -len(source) <= axis < len(source):
            raise _fail(node, f"axis {axis} out of range for rank {len(source)}")
        axis %= len(source)
        index = constants.get(node.inputs[1])
        if index is None or index.shape != () or source[axis] != 1 or int(index) not in (0, -1):
            raise _fail(
                node, "only a constant scalar index into an axis of size 1 is supported (y[0] of one step)"
            )
        return tuple(d for i, d in enumerate(source) if i != axis)


class Constant(Emitter):
    """Handled by the importer: its value becomes a graph constant; no code."""

    attrs: ClassVar[Mapping[str, AttrValue]] = {"value": 0}
    min_inputs = max_inputs = 0

    def check(self, node: Node, shapes: Mapping[str, Shape], constants: Mapping[str, np.ndarray]) -> Shape:
        return constants[node.outputs[0]].shape

    def emit(self, node: Node, ctx: EmitContext, n: int) -> list[str]:
        return []
