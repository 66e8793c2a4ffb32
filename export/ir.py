"""The small frozen IR between ONNX and C.

A :class:`Graph` maps one observation to one action through :class:`Node` objects in topological
order over float32 values with static shapes (batch dimension fixed to 1). A recurrent policy also
carries state: each :attr:`Graph.states` pair is a value read at the step's start and the value that
replaces it for the next step (an LSTM's hidden and cell state). Constants are read-only numpy arrays.
Emitters see only this IR, never protobuf objects.
"""

from __future__ import annotations

from collections.abc import Mapping
from dataclasses import dataclass
from types import MappingProxyType
from typing import Any

import numpy as np

AttrValue = int | float | str | tuple[int, ...] | tuple[float, ...] | tuple[str, ...]


@dataclass(frozen=True)
class Node:
    """One operation: ``outputs = op(inputs; attrs)``."""

    op: str
    name: str
    inputs: tuple[str, ...]
    outputs: tuple[str, ...]
    attrs: Mapping[str, AttrValue]

    def attr(self, key: str, default: Any) -> Any:
        return self.attrs.get(key, default)


@dataclass(frozen=True)
class Graph:
    """A validated graph: every value has a static shape, every node passed its emitter's check."""

    input: str
    output: str
    nodes: tuple[Node, ...]
    shapes: Mapping[str, tuple[int, ...]]
    """Static shape of every value (graph input, constants and node outputs)."""
    constants: Mapping[str, np.ndarray]
    """Initializers and Constant outputs, read-only (float32, or int64 for shape operands)."""
    states: tuple[tuple[str, str], ...] = ()
    """(state read by the step, its value for the next step) pairs of equal shape, zero at reset."""

    @staticmethod
    def freeze(
        input: str,
        output: str,
        nodes: list[Node],
        shapes: dict[str, tuple[int, ...]],
        constants: dict[str, np.ndarray],
        states: tuple[tuple[str, str], ...] = (),
    ) -> Graph:
        frozen = {}
        for name, array in constants.items():
            a = np.array(array, copy=True)
            a.setflags(write=False)
            frozen[name] = a
        return Graph(
            input,
            output,
            tuple(nodes),
            MappingProxyType(dict(shapes)),
            MappingProxyType(frozen),
            tuple(states),
        )

    def size(self, value: str) -> int:
        """Number of elements of a value."""
        return int(np.prod(self.shapes[value], dtype=np.int64))

    @property
    def state_size(self) -> int:
        """Floats of state carried from one step to the next (0: a feed-forward policy)."""
        return sum(self.size(read) for read, _ in self.states)

    def is_constant(self, value: str) -> bool:
        return value in self.constants
