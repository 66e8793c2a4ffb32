"""The small frozen IR between ONNX and C.

A :class:`Graph` is a single-input, single-output chain of :class:`Node` objects in topological
order over float32 values with static shapes (batch dimension fixed to 1). Constants are
read-only numpy arrays. Emitters see only this IR, never protobuf objects.
"""

from __future__ import annotations

from collections.abc import Mapping
from dataclasses import dataclass
from types import MappingProxyType
from typing import Any

import numpy as np

AttrValue = int | float | str | tuple[int, ...] | tuple[float, ...]


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

    @staticmethod
    def freeze(
        input: str,
        output: str,
        nodes: list[Node],
        shapes: dict[str, tuple[int, ...]],
        constants: dict[str, np.ndarray],
    ) -> Graph:
        frozen = {}
        for name, array in constants.items():
            a = np.array(array, copy=True)
            a.setflags(write=False)
            frozen[name] = a
        return Graph(input, output, tuple(nodes), MappingProxyType(dict(shapes)), MappingProxyType(frozen))

    def size(self, value: str) -> int:
        """Number of elements of a value."""
        return int(np.prod(self.shapes[value], dtype=np.int64))

    def is_constant(self, value: str) -> bool:
        return value in self.constants
