"""The one interpreter: a graph evaluated on a batch of observations with the ops' NumPy references.

``float64`` gives every value of the graph as the ops mean it (calibration of q15's fixed-point
scales); ``int8`` gives bit for bit what the generated ``--quantize int8`` C computes (the export's
exact model of its arithmetic). A q15 ``section`` replaces the nodes it covers with its own integer
model (:func:`embedrl.export.fixed_point.run`).
"""

from __future__ import annotations

from typing import Protocol

import numpy as np

from embedrl.export.errors import UnsupportedOpError
from embedrl.export.ir import Graph
from embedrl.export.ops import EMITTERS
from embedrl.export.ops.base import PRECISIONS


class Section(Protocol):
    """Nodes of the graph evaluated together by their own model (q15's :class:`~embedrl.export.fixed_point.
    FixedSection`): from the value ``input`` to the value ``output``."""

    @property
    def input(self) -> str: ...
    @property
    def output(self) -> str: ...
    @property
    def nodes(self) -> frozenset[str]: ...
    @property
    def first_node(self) -> str: ...
    def run(self, x: np.ndarray) -> np.ndarray:
        """The section's output for a batch of inputs."""
        ...


def run(
    graph: Graph, obs: np.ndarray, precision: str, section: Section | None = None
) -> dict[str, np.ndarray]:
    """Every value of ``graph`` for the observations ``obs`` [B, obs_dim], rows independent."""
    if precision not in PRECISIONS:
        raise ValueError(f"unknown precision {precision!r}; use one of {PRECISIONS}")
    dtype = np.float64 if precision == "float64" else np.float32
    values: dict[str, np.ndarray] = {graph.input: np.asarray(obs, dtype).reshape(len(obs), -1)}

    def get(name: str) -> np.ndarray:
        return values[name] if name in values else np.asarray(graph.constants[name], dtype).reshape(-1)

    for node in graph.nodes:
        if section is not None and node.name in section.nodes:
            if node.name == section.first_node:
                values[section.output] = section.run(get(section.input))
            continue
        emitter = EMITTERS[node.op]
        if precision == "int8" and not emitter.quantizable:
            raise UnsupportedOpError(f"{node.op} node '{node.name}' is not supported with --quantize int8")
        inputs = [get(name) for name in node.inputs if name]
        values[node.outputs[0]] = emitter.reference(node, inputs, graph.constants, precision)
    return values
