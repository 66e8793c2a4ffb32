"""The policy layer by layer, as ST Edge AI's analyze report lists it: each IR node of the export's ONNX
(``export.onnx_import.to_ir``) with its shapes, its multiply-accumulates, the bytes of constant data the
generated C holds for it, the RAM of its output and its share of each target's estimated cycles.

The weight bytes are read from the deployed file, not computed from a precision's layout: each ``static
const`` array of ``c/<name>.c`` is attributed to the node whose name or constant input it is named after
(the identifier that starts the comment the generator writes above each ``<name>_w<k>``); an array
named after none stays unattributed, in its own
row, and the total is checked against the generated header's own count.
"""

from __future__ import annotations

import re
from pathlib import Path
from typing import Any

from embedrl.escape import identifier
from embedrl.export.ops import multiply_adds

FLOAT_BYTES = 4
"""Activations are float32 between layers (a q15 section's int16 buffers are inside its layers)."""
C_TYPE_BYTES = {"float": 4, "int8_t": 1, "uint8_t": 1, "int16_t": 2, "int32_t": 4, "int64_t": 8}
_CONST = re.compile(r"^/\* (\w+): [^\n]*\*/\nstatic const (\w+) (\w+)((?:\[\d+\])+) = \{", re.M)
"""A weight array with the comment the generator writes above it (``export.codegen.const_comment``)."""
_HEADER_WEIGHTS = re.compile(r"weights: (\d+) bytes of const data")
_HOST_ONLY = re.compile(
    r"^#if (defined\(__x86_64__\)|!\(defined\(__ARM_ARCH_PROFILE\))[^\n]*\n.*?^#endif", re.M | re.S
)
"""A block of the generated C that only the host compiles (its layouts of the weights)."""


def layer_table(export_dir: Path, export: dict[str, Any]) -> dict[str, Any]:
    """``{"rows": [...], "unattributed_bytes", "header_weight_bytes", "weight_bytes"}``: one row per node
    (``op``, ``name``, ``input_shape``, ``output_shape``, ``macs``, ``weight_bytes``, ``activation_bytes``,
    ``cycles`` per target)."""
    from embedrl.export.onnx_import import load_onnx
    from embedrl.export.qdq import lowered

    graph = lowered(load_onnx(export_dir / "policy.onnx"))[0]
    name = export["name"]
    arrays = const_arrays((export_dir / "c" / f"{name}.c").read_text(), name)
    header = _HEADER_WEIGHTS.search((export_dir / "c" / f"{name}.h").read_text())
    owners: dict[str, str] = {}
    for node in graph.nodes:
        for key in (node.name, *(i for i in node.inputs if graph.is_constant(i))):
            owners.setdefault(_sanitize(key), node.name)
    per_node: dict[str, int] = {}
    unattributed = 0
    for key, size in arrays:
        if key in owners:
            per_node[owners[key]] = per_node.get(owners[key], 0) + size
        else:
            unattributed += size
    rows: list[dict[str, Any]] = []
    for node in graph.nodes:
        emitter_alias = _is_alias(node.op)
        rows.append({
            "op": node.op, "name": node.name,
            "input_shape": list(graph.shapes[node.inputs[0]]),
            "output_shape": list(graph.shapes[node.outputs[0]]),
            "macs": multiply_adds(node, graph), "weight_bytes": per_node.get(node.name, 0),
            "activation_bytes": 0 if emitter_alias else FLOAT_BYTES * graph.size(node.outputs[0]),
            "work": _work(node, graph, emitter_alias),
        })  # fmt: skip
    total_work = sum(r["work"] for r in rows) or 1
    for row in rows:
        row["cycles"] = {
            target: round(t["estimated_cycles_per_inference"] * row["work"] / total_work)
            for target, t in export.get("targets", {}).items()
        }
        del row["work"]
    return {
        "rows": rows,
        "weight_bytes": sum(size for _, size in arrays),
        "unattributed_bytes": unattributed,
        "header_weight_bytes": int(header.group(1)) if header else None,
    }


def const_arrays(source: str, name: str) -> list[tuple[str, int]]:
    """(key, bytes) of each ``static const`` weight array of a generated ``<name>.c`` (``key``: the
    identifier the generator's comment above ``<name>_w<k>`` starts with) as a Cortex-M target compiles it,
    as the
    header's count does: the host's own layouts of the weights (input-major float rows, int16 rows for AVX2)
    are left out. The safe action is not a weight."""
    out = []
    prefix = re.compile(rf"{re.escape(name)}_w\d+")
    for key, ctype, symbol, dims in _CONST.findall(_HOST_ONLY.sub("", source)):
        if not prefix.fullmatch(symbol):
            continue
        count = 1
        for d in re.findall(r"\d+", dims):
            count *= int(d)
        out.append((key, count * C_TYPE_BYTES[ctype]))
    return out


def _work(node: Any, graph: Any, alias: bool) -> int:
    """What a node's share of the cycles is apportioned by: its MACs, or one per output element."""
    if alias:
        return 0
    return multiply_adds(node, graph) or graph.size(node.outputs[0])


def _is_alias(op: str) -> bool:
    from embedrl.export.ops import EMITTERS

    return bool(EMITTERS[op].alias)


def _sanitize(key: str) -> str:
    """The identifier of a constant's key in the generator's comment (``export.codegen.const_comment``)."""
    return identifier(key.split("#")[0])
