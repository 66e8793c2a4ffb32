"""Is an export's C what embedrl generates from its ONNX? Then it may be compiled and run on this host.

An export folder received from someone else is untrusted input, like a model file: its ``c/`` may hold any
code (a bias changed, a ``__attribute__((constructor))`` appended). Code generation is deterministic, so
the check is exact: the C is generated again from the folder's ``policy.onnx`` with the settings its
``export_report.json`` records (name, precision, safe action, interface, the provenance lines, a q15
section calibrated on the folder's own observations) and compared byte for byte with ``c/``. Only an
export whose C is identical gets built and run; any other is named, and none of its code runs.
"""

from __future__ import annotations

from dataclasses import dataclass
from pathlib import Path
from typing import Any

import numpy as np

from embedrl.common import read_json, sha256
from embedrl.export.errors import ExportError
from embedrl.export.interpret import Section
from embedrl.export.ir import Graph

OBSERVATIONS = Path("test") / "observations.npy"


@dataclass(frozen=True)
class Regenerated:
    """What an export's C is made from, read again from its folder, and the C generated from it."""

    graph: Graph
    section: Section | None
    """A q15 export's fixed-point section, calibrated on the folder's observations as the export did."""
    observations: np.ndarray
    """The export's verification observations (float32)."""
    files: dict[str, str]
    problem: str | None
    """None if ``c/`` is exactly ``files``; else which file differs."""


def regenerate(export_dir: Path) -> Regenerated | str:
    """The export's C generated again and compared with ``c/``; a string (one line) where the folder does not
    allow it (never raises for a damaged folder)."""
    try:
        graph, section, observations, files = _generated(export_dir)
    except (ExportError, OSError, ValueError, KeyError, TypeError) as exc:
        return f"the C cannot be generated again from {export_dir / 'policy.onnx'}: {exc}"
    return Regenerated(graph, section, observations, files, _compare(export_dir, files))


def mismatch(export_dir: Path) -> str | None:
    """None if every file in ``export_dir/c`` is exactly what this embedrl generates from the folder's ONNX;
    else one line saying which file differs or why the C cannot be generated again."""
    result = regenerate(export_dir)
    return result if isinstance(result, str) else result.problem


def _compare(export_dir: Path, expected: dict[str, str]) -> str | None:
    c_dir = export_dir / "c"
    present = sorted(p.name for p in c_dir.iterdir()) if c_dir.is_dir() else []
    if present != sorted(expected):
        return f"{c_dir} holds {present}, the generator writes {sorted(expected)}"
    for filename, text in sorted(expected.items()):
        if (c_dir / filename).read_bytes() != text.encode():
            return f"{c_dir / filename} is not what embedrl generates from policy.onnx (edited since?)"
    return None


def _generated(export_dir: Path) -> tuple[Graph, Section | None, np.ndarray, dict[str, str]]:
    from embedrl.export.codegen import generate
    from embedrl.export.onnx_import import load_onnx
    from embedrl.export.pipeline import tool_version
    from embedrl.export.qdq import lowered
    from embedrl.export.quantize import plan_section
    from embedrl.train.interface import Interface

    report: dict[str, Any] = read_json(export_dir / "export_report.json")
    tool = f"embedrl {tool_version()}"
    if report["tool"] != tool:
        raise ExportError(f"it was exported by {report['tool']}, this is {tool}")
    onnx_path = export_dir / "policy.onnx"
    graph, given = lowered(load_onnx(onnx_path))
    quantize = report["quantize"]
    observations = np.load(export_dir / OBSERVATIONS, allow_pickle=False).astype(np.float32)
    if observations.ndim != 2 or observations.shape[1] != graph.size(graph.input):
        raise ValueError(f"{OBSERVATIONS} holds {observations.shape}, not rows of the policy's observations")
    section = plan_section(graph, quantize, observations, given)
    interface_file = export_dir / "interface.json"
    interface = Interface.from_json(read_json(interface_file)) if interface_file.is_file() else None
    source = report["source"]
    header = {
        "tool": tool,
        "source": f"{Path(source['path']).name} sha256 {source['sha256']}",
        "onnx": f"sha256 {sha256(onnx_path)}",
    }
    safe = (
        list(interface.safe_action)
        if interface is not None
        else report["verification"]["non_finite_observation"]["action"]
    )
    files = generate(
        graph, report["name"], safe, header, quantize=quantize, section=section, interface=interface
    )
    return graph, section, observations, files
