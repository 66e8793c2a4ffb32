"""The paths matrix: every way through the chain, source x precision x node x sandbox x scenario.

Sources: each algorithm's shipped SB3 zip, the moving-shelf and two-robot scenarios' policies, and an
ONNX from elsewhere (input ``x``, output ``y``, no embedrl metadata) exported by a relative path from
another working folder into a folder whose path has spaces. Each source is exported once per precision
(float32, int8-weights, q15) with the closed loop skipped; the HIL run then compares the node with the
export's own reference for that precision (:mod:`embedrl.export.reference`).

Every source x precision through the Python reference node, and through the compiled C node over vcan in
the shared guest (``--sandbox auto``), plus rows on the session's QEMU guest (``qemu_guest``, shared with the
other QEMU tests) that cover every precision, every scenario and the foreign ONNX there: every pair of values
of the five factors meets in at least one row (:data:`C_ROWS`, checked by a test). The 21 exports take
minutes: the matrix is in the slow tier.
"""

from __future__ import annotations

import itertools
import os
from pathlib import Path
from typing import Any

import onnx
import pytest

from embedrl.cli import main
from embedrl.hil.sandbox import Guest
from tests.conftest import marks_its_users
from tests.hil.helpers import hil

ROOT = Path(__file__).resolve().parents[2]
POLICIES = ROOT / "policies"
SOURCES = {
    "ddpg": ("static", POLICIES / "static" / "ddpg.zip"),
    "td3": ("static", POLICIES / "static" / "td3.zip"),
    "sac": ("static", POLICIES / "static" / "sac.zip"),
    "ppo": ("static", POLICIES / "static" / "ppo.zip"),
    "onnx": ("static", None),  # the foreign ONNX, made from the TD3 export
    "moving-shelf td3": ("moving-shelf", POLICIES / "moving-shelf" / "td3.zip"),
    "two-robots td3": ("two-robots", POLICIES / "two-robots" / "td3.zip"),
}
PRECISIONS = ("float32", "int8-weights", "q15")
PYTHON_ROWS = list(itertools.product(SOURCES, PRECISIONS))
"""Every source at every precision through the Python node."""
C_ROWS = [(s, p, "auto") for s, p in itertools.product(SOURCES, PRECISIONS)] + [
    ("td3", "float32", "qemu"),
    ("onnx", "int8-weights", "qemu"),
    ("sac", "q15", "qemu"),
    ("ddpg", "int8-weights", "qemu"),
    ("ppo", "q15", "qemu"),
    ("moving-shelf td3", "float32", "qemu"),
    ("two-robots td3", "int8-weights", "qemu"),
]
"""The slow suite: (source, precision, sandbox) through the C node."""


def _foreign_onnx(folder: Path, float_export: Path) -> Path:
    """The TD3 export's ONNX as a file from elsewhere: renamed input and output, no metadata."""
    model = onnx.load(str(float_export / "policy.onnx"))
    graph = model.graph
    renames = {graph.input[0].name: "x", graph.output[0].name: "y"}
    for node in graph.node:
        node.input[:] = [renames.get(i, i) for i in node.input]
        node.output[:] = [renames.get(o, o) for o in node.output]
    graph.input[0].name, graph.output[0].name = "x", "y"
    del model.metadata_props[:]
    path = folder / "models from elsewhere" / "foreign policy.onnx"
    path.parent.mkdir(parents=True, exist_ok=True)
    onnx.save(model, str(path))
    return path


@pytest.fixture(scope="session")
@marks_its_users("slow")  # 21 exports
def exports(tmp_path_factory: pytest.TempPathFactory) -> dict[tuple[str, str], Path]:
    """Every source exported at every precision (closed loop skipped), into folders with spaces."""
    base = tmp_path_factory.mktemp("paths") / "exports with spaces"
    made: dict[tuple[str, str], Path] = {}
    for source, precision in PYTHON_ROWS:
        scenario, path = SOURCES[source]
        out = base / f"{source} {precision}"
        quantize = [] if precision == "float32" else ["--quantize", precision]
        if path is None:  # by a relative path, from the folder that holds the model's folder
            model = _foreign_onnx(base.parent, made[("td3", "float32")])
            previous = os.getcwd()
            os.chdir(model.parent.parent)
            try:
                argv = ["export", str(model.relative_to(model.parent.parent)), "--out", os.path.relpath(out)]
                assert main([*argv, "--episodes", "0", *quantize]) == 0
            finally:
                os.chdir(previous)
        else:
            argv = ["export", str(path), "--out", str(out), "--scenario", scenario, "--episodes", "0"]
            assert main([*argv, *quantize]) == 0
        made[(source, precision)] = out
    return made


def _check(report: dict[str, Any], precision: str) -> None:
    assert report["verdict"]["passed"], report["verdict"]
    assert report["precision"] == precision
    assert report["max_action_abs_diff"] is not None and report["max_action_abs_diff"] <= 1e-5
    assert report["rx_timeouts"] == 0


def test_an_export_folder_is_self_contained_and_movable(
    exports: dict[tuple[str, str], Path], tmp_path: Path
) -> None:
    moved = tmp_path / "moved elsewhere"
    exports[("onnx", "float32")].rename(moved)
    try:
        assert (moved / "policy.onnx").is_file()
        report = hil(None, moved, tmp_path, "--node", "python", "--episodes", "1")
        _check(report, "float32")
    finally:
        moved.rename(exports[("onnx", "float32")])


@pytest.mark.parametrize(("source", "precision"), PYTHON_ROWS)
def test_every_source_and_precision_through_the_python_node(
    source: str, precision: str, exports: dict[tuple[str, str], Path], tmp_path: Path
) -> None:
    report = hil(None, exports[(source, precision)], tmp_path, "--node", "python", "--episodes", "1")
    _check(report, precision)
    assert report["sandbox"] == "none"


def _marked(row: tuple[str, str, str]) -> Any:
    """A C row as a test parameter with the tiers of the guest the test asks for by name (``guest`` or
    ``qemu_guest``: fixtures looked up at run time mark nothing at collection)."""
    qemu = [pytest.mark.qemu] if row[2] == "qemu" else []
    return pytest.param(*row, marks=[pytest.mark.sandbox, *qemu])


@pytest.mark.slow
@pytest.mark.parametrize(("source", "precision", "where"), [_marked(row) for row in C_ROWS])
def test_the_c_node_over_vcan_on_a_pairwise_cover(
    source: str,
    precision: str,
    where: str,
    exports: dict[tuple[str, str], Path],
    tmp_path: Path,
    request: pytest.FixtureRequest,
) -> None:
    guest: Guest = request.getfixturevalue("guest" if where == "auto" else "qemu_guest")
    report = hil(guest, exports[(source, precision)], tmp_path, "--episodes", "1")
    _check(report, precision)
    assert report["sandbox"] == guest.provider
    assert report["node_diag"] is None or report["node_diag"]["action_faults"] == 0


def test_the_c_rows_cover_every_pair_of_values() -> None:
    sandboxes = {"auto", "qemu"}
    rows = [(SOURCES[s][0], s, p, w) for s, p, w in C_ROWS]
    factors = [
        {SOURCES[s][0] for s in SOURCES},  # scenario
        set(SOURCES),
        set(PRECISIONS),
        sandboxes,
    ]
    for (i, a), (j, b) in itertools.combinations(enumerate(factors), 2):
        for x, y in itertools.product(a, b):
            if i == 0 and j == 1 and SOURCES[y][0] != x:
                continue  # a source belongs to one scenario
            assert any(r[i] == x and r[j] == y for r in rows), (x, y)
