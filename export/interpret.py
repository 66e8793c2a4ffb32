"""The one interpreter: a graph evaluated on a batch of observations with the ops' NumPy references.

``float64`` gives every value of the graph as the ops mean it (calibration of q15's fixed-point
scales); ``int8`` gives bit for bit what the generated ``--quantize int8`` C computes (the export's
exact model of its arithmetic). A q15 ``section`` replaces the nodes it covers with its own integer
model (:func:`embedrl.export.fixed_point.run`).
"""

from __future__ import annotations

from collections.abc import Mapping
from typing import Protocol

import numpy as np

from embedrl.export.errors import UnsupportedOpError
from embedrl.export.ir import Graph
from embedrl.export.ops import EMITTERS
from embedrl.export.ops.base import PRECISIONS, EmitContext


class Section(Protocol):
    """Nodes of the graph evaluated together by their own integer model (q15's :class:`~embedrl.export.
    fixed_point.FixedSection`, int8-full's :class:`~embedrl.export.full_integer.IntegerSection`): from the
    value ``input`` to the value ``output``."""

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

    def c_lines(self, ctx: EmitContext) -> tuple[list[str], list[str]]:
        """The section's C statements (they return the safe action on a non-finite input before converting
        it to integers) and the declarations of its buffers."""
        ...

    def c_includes(self, prefix: str) -> list[str]:
        """Preprocessor lines the section needs among the file's includes (MISRA C:2012 rule 20.1)."""
        ...

    def ram_bytes(self) -> int:
        """RAM of the section's own buffers."""
        ...


def run(
    graph: Graph,
    obs: np.ndarray,
    precision: str,
    section: Section | None = None,
    state: Mapping[str, np.ndarray] | None = None,
) -> dict[str, np.ndarray]:
    """Every value of ``graph`` for the observations ``obs`` [B, obs_dim], rows independent; a recurrent
    graph's state values from ``state`` (each [B, n]; zeros when absent)."""
    if precision not in PRECISIONS:
        raise ValueError(f"unknown precision {precision!r}; use one of {PRECISIONS}")
    dtype = np.float64 if precision == "float64" else np.float32
    values: dict[str, np.ndarray] = {graph.input: np.asarray(obs, dtype).reshape(len(obs), -1)}
    for read, _ in graph.states:
        given = (state or {}).get(read)
        values[read] = (
            np.zeros((len(obs), graph.size(read)), dtype) if given is None else np.asarray(given, dtype)
        )

    def get(name: str) -> np.ndarray:
        return values[name] if name in values else np.asarray(graph.constants[name], dtype).reshape(-1)

    for node in graph.nodes:
        if section is not None and node.name in section.nodes:
            if node.name == section.first_node:
                values[section.output] = section.run(get(section.input))
            continue
        emitter = EMITTERS[node.op]
        if precision == "int8" and not emitter.quantizable:
            raise UnsupportedOpError(
                f"{node.op} node '{node.name}' is not supported with --quantize int8-weights"
            )
        inputs = [get(name) for name in node.inputs if name]
        result = emitter.reference(node, inputs, graph.constants, precision)
        if len(node.outputs) == 1:
            values[node.outputs[0]] = result
        else:
            values.update((out, result[k]) for k, out in enumerate(node.outputs) if out)
    return values


def run_sequence(graph: Graph, observations: np.ndarray, precision: str = "float64") -> np.ndarray:
    """The actions [T, act_dim] of one episode's observations [T, obs_dim] from zero state, the state
    carried from each step to the next (a feed-forward graph: each row on its own)."""
    state: dict[str, np.ndarray] = {}
    actions = []
    for row in np.asarray(observations).reshape(len(observations), -1):
        values = run(graph, row[None], precision, state=state)
        actions.append(values[graph.output][0])
        state = {read: values[write] for read, write in graph.states}
    return np.asarray(actions).reshape(len(actions), -1)
