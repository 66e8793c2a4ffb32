"""Is an export's C what embedrl generates from its ONNX? Then it may be compiled and run on this host.

An export folder received from someone else is untrusted input, like a model file: its ``c/`` may hold any
code (a bias changed, a ``__attribute__((constructor))`` appended), and so may its CAN code (``can/``,
``can-fd/``). Code generation is deterministic, so the check is exact: the C is generated again from the
folder's ``policy.onnx`` with the settings its ``export_report.json`` records (name, precision, safe action,
interface, the provenance lines, a q15 section calibrated on the folder's own observations) and compared
byte for byte with ``c/``; the CAN code is generated again from its ``interface.json`` and compared with its
folders. Only an export whose C is identical gets built and run; any other is named, and none of its code
runs. An export made before exports carried their CAN code has none of its folders: nothing to compare
there (``embedrl hil run`` generates that code itself).
"""

from __future__ import annotations

from dataclasses import dataclass
from pathlib import Path, PurePosixPath
from typing import Any

import numpy as np

from embedrl.common import read_json, sha256
from embedrl.export.contract import sources as can_sources
from embedrl.export.errors import ExportError
from embedrl.export.interpret import Section
from embedrl.export.ir import Graph
from embedrl.train.interface import INTERFACE_FILE, Interface

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
    """``c/``: file name -> text."""
    can_files: dict[str, str]
    """The CAN code: path in the folder (``can/policy_io.c``) -> text."""
    problem: str | None
    """None if ``c/`` is exactly ``files`` and the CAN folders ``can_files`` (or absent, an older export);
    else which file differs."""


def regenerate(export_dir: Path, interface: Interface | None = None) -> Regenerated | str:
    """The export's C generated again and compared with ``c/`` and its CAN folders; a string (one line) where
    the folder does not allow it (never raises for a damaged folder). ``interface``: the folder's
    ``interface.json``, if the caller has read it already."""
    try:
        if interface is None and (export_dir / INTERFACE_FILE).is_file():
            interface = Interface.from_json(read_json(export_dir / INTERFACE_FILE))
        graph, section, observations, files, can = _generated(export_dir, interface)
    except (ExportError, OSError, ValueError, KeyError, TypeError) as exc:
        return f"the C cannot be generated again from {export_dir / 'policy.onnx'}: {exc}"
    problem = _compare(export_dir, files) or _compare_can(export_dir, can)
    return Regenerated(graph, section, observations, files, can, problem)


def mismatch(export_dir: Path, interface: Interface | None = None) -> str | None:
    """None if every file in ``export_dir/c`` is exactly what this embedrl generates from the folder's ONNX,
    and every CAN folder what it generates from its interface; else one line saying which file differs or
    why the C cannot be generated again."""
    result = regenerate(export_dir, interface)
    return result if isinstance(result, str) else result.problem


def _compare_can(export_dir: Path, expected: dict[str, str]) -> str | None:
    folders = sorted({PurePosixPath(path).parts[0] for path in expected} | set(can_sources.FOLDERS))
    if not any((export_dir / folder).exists() for folder in folders):
        return None  # made before exports carried their CAN code
    for folder in folders:
        wanted = sorted(PurePosixPath(p).name for p in expected if PurePosixPath(p).parts[0] == folder)
        here = export_dir / folder
        present = sorted(p.name for p in here.iterdir()) if here.is_dir() else []
        if present != wanted:
            return f"{here} holds {present}, the generator writes {wanted}"
    for path, text in sorted(expected.items()):
        if (export_dir / path).read_bytes() != text.encode():
            return f"{export_dir / path} is not what embedrl generates from {INTERFACE_FILE} (edited since?)"
    return None


def _compare(export_dir: Path, expected: dict[str, str]) -> str | None:
    c_dir = export_dir / "c"
    present = sorted(p.name for p in c_dir.iterdir()) if c_dir.is_dir() else []
    if present != sorted(expected):
        return f"{c_dir} holds {present}, the generator writes {sorted(expected)}"
    for filename, text in sorted(expected.items()):
        if (c_dir / filename).read_bytes() != text.encode():
            return f"{c_dir / filename} is not what embedrl generates from policy.onnx (edited since?)"
    return None


def _generated(
    export_dir: Path, interface: Interface | None
) -> tuple[Graph, Section | None, np.ndarray, dict[str, str], dict[str, str]]:
    from embedrl.export.codegen import generate
    from embedrl.export.onnx_import import load_onnx
    from embedrl.export.pipeline import tool_version
    from embedrl.export.qdq import lowered
    from embedrl.export.quantize import plan_section
    from embedrl.export.reference import check_scheme
    from embedrl.export.report_schema import check_export_report

    report: dict[str, Any] = read_json(export_dir / "export_report.json")
    check_export_report(report)
    tool = f"embedrl {tool_version()}"
    if report["tool"] != tool:
        raise ExportError(f"it was exported by {report['tool']}, this is {tool}")
    onnx_path = export_dir / "policy.onnx"
    graph, given = lowered(load_onnx(onnx_path))
    quantize = report["quantize"]
    check_scheme(report, export_dir / "export_report.json")
    observations = np.load(export_dir / OBSERVATIONS, allow_pickle=False).astype(np.float32)
    if observations.ndim != 2 or observations.shape[1] != graph.size(graph.input):
        raise ValueError(f"{OBSERVATIONS} holds {observations.shape}, not rows of the policy's observations")
    section = plan_section(graph, quantize, observations, given)
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
    can = {} if interface is None else can_sources.export_files(interface, report["name"])[0]
    return graph, section, observations, files, can
