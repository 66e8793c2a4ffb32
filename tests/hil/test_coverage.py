"""Coverage of the deployed C (``make -C runtime_c coverage``, the report's coverage check): the shipped TD3's
policy and the node measured with clang-19, the summary's figures and gaps, and the check's refusals."""

from __future__ import annotations

import shutil
import subprocess
import sys
from pathlib import Path
from typing import Any

import numpy as np
import pytest

from embedrl.export.build import RUNTIME_C
from embedrl.hil.signoff import coverage, facts
from tests.conftest import Exported
from tests.hil.conftest import SHIPPED_TD3


@pytest.fixture(scope="module")
def measured(exported: Exported, tmp_path_factory: pytest.TempPathFactory) -> dict[str, Any]:
    """The shipped TD3's export measured from a folder with a space in its path (make reaches it through a
    link; llvm-cov must still name sources that can be read)."""
    export = tmp_path_factory.mktemp("coverage") / "with space"
    shutil.copytree(exported(SHIPPED_TD3, "--episodes", "0"), export)
    summary = facts.coverage(export, facts.load_export(export), {"generated_c": facts.IDENTICAL})
    assert not isinstance(summary, str), summary
    return summary


def _file(summary: dict[str, Any], name: str) -> dict[str, Any]:
    return next(f for f in summary["files"] if f["file"] == name)


def test_the_shipped_td3_policy_is_covered_entirely_by_its_verification_vectors_and_probes(
    measured: dict[str, Any],
) -> None:
    policy = _file(measured, "policy.c")
    assert policy["lines"]["covered"] == policy["lines"]["count"] > 80  # the deployable step (no batch)
    assert policy["branches"]["covered"] == policy["branches"]["count"] > 40
    assert policy["mcdc"]["count"] == 0  # every decision of the generated C has one condition
    assert policy["gaps"] == [] and policy["meets_goal"]
    probes = measured["probes"]
    assert probes["verification_rows"] == 10_000 and probes["rows"] == 10_000 + 7 * 6 + 4
    # NaN, +inf and -inf at each of the 6 positions: refused as observations; the overflow probes that
    # make the network's own sums non-finite: refused as its result
    assert probes["codes"]["1"] == 18 and probes["codes"]["2"] == 14
    assert sum(probes["codes"].values()) == probes["rows"]


def test_the_node_and_its_can_glue_reach_the_goal_or_say_why_not(measured: dict[str, Any]) -> None:
    assert [f["file"] for f in measured["files"]] == [
        "policy.c", "node.c", "e2e.c", "policy_io.c", "slcan.c", "policy_dbc.c"
    ]  # fmt: skip
    for name in ("e2e.c", "slcan.c", "node.c", "policy_io.c"):
        f = _file(measured, name)
        assert f["in_goal"] and all(g["reason"] for g in f["gaps"]), f["gaps"]
        mcdc = coverage.percent(f["mcdc"])
        assert mcdc is None or mcdc >= coverage.GOAL_MCDC, (name, f["mcdc"])
    assert _file(measured, "e2e.c")["gaps"] == []
    node_gaps = {(g["line"], g["kind"]) for g in _file(measured, "node.c")["gaps"]}
    assert {kind for _, kind in node_gaps} == {"branch", "condition"}  # every line of node.c runs
    assert not _file(measured, "policy_dbc.c")["in_goal"]
    passed, detail = coverage.check(measured)
    assert passed and "policy.c lines 86/86 (100%), branches 44/44 (100%), MC/DC none" in detail
    assert detail.endswith(
        "; 5 gap(s), each with its reason; merged from the verification vectors, the C tests (no HIL run "
        "with coverage)"
    )
    assert measured["compiler"]["version"].startswith("Debian clang")
    assert (
        measured["compiler"]["command"].startswith("clang-19 ")
        and "-fcoverage-mcdc" in measured["compiler"]["command"]
    )


def _export_json(source: Path, branches: list[list[int]], mcdc: list[list[Any]]) -> dict[str, Any]:
    counts = {"count": 2, "covered": 1}
    summary = {"lines": {"count": 3, "covered": 3}, "branches": counts, "mcdc": counts}
    files = [{"filename": str(source), "summary": summary, "branches": branches, "mcdc_records": mcdc}]
    return {"version": "2.0.1", "data": [{"files": files}]}


def test_a_gap_without_a_reason_fails_the_check_and_names_its_place(tmp_path: Path) -> None:
    source = tmp_path / "e2e.c"
    source.write_text("int f(int a, int b)\n{\n    return a && b;\n}\n")
    branches = [[3, 12, 3, 13, 4, 1, 0, 0, 6], [3, 17, 3, 18, 1, 0, 0, 0, 6]]
    mcdc = [[3, 12, 3, 18, 0, 5, [True, False]]]
    lcov = f"SF:{source}\nDA:1,5\nDA:3,5\nend_of_record\n"
    summary = coverage.summarise(_export_json(source, branches, mcdc), lcov, "policy.c", [])
    gaps = summary["files"][0]["gaps"]
    assert [(g["line"], g["kind"], g["code"], g["detail"][:12]) for g in gaps] == [
        (3, "branch", "b", "never false"),
        (3, "condition", "b", "not shown to"),
    ]
    passed, detail = coverage.check(summary)
    assert not passed and detail.startswith(
        "2 gap(s) without a reason, first e2e.c:3 `b` (branch, never false)"
    )
    reasons = [
        coverage.Reason("e2e.c", "branch", "b", "why"),
        coverage.Reason("e2e.c", "condition", "b", "why"),
    ]
    assert coverage.check(
        coverage.summarise(_export_json(source, branches, mcdc), lcov, "policy.c", reasons)
    )[0]


def test_the_committed_reasons_for_the_node_each_explain_a_gap_that_exists(measured: dict[str, Any]) -> None:
    """A reason for the node's files (the same for every export) left behind after its gap was covered, or
    its code changed, is named. The generated policy's reasons are for other ops' and precisions' code."""
    node = [r for r in coverage.load_reasons() if r.file != "policy.c"]
    used = {
        (f["file"], r.kind, r.code)
        for f in measured["files"]
        for g in f["gaps"]
        for r in node
        if r.file == f["file"] and coverage.explains(r, g)
    }
    assert {(r.file, r.kind, r.code) for r in node} == used


def test_without_clang_19_make_coverage_refuses_in_one_line(tmp_path: Path) -> None:
    obs = tmp_path / "obs.f32"
    np.zeros((1, 6), dtype="<f4").tofile(obs)
    result = subprocess.run(
        ["make", "--no-print-directory", "-C", str(RUNTIME_C), "coverage", "COV_CC=clang-404",
         f"POLICY_DIR={tmp_path}", f"COVERAGE_OBS={obs}", f"BUILD_DIR={tmp_path / 'b'}",
         f"PYTHON={sys.executable}"],
        capture_output=True, text=True,
    )  # fmt: skip
    assert result.returncode == 2
    assert result.stderr.splitlines()[0] == (
        "coverage needs clang-404: apt-get install clang-19 llvm-19 (or set COV_CC, LLVM_PROFDATA, LLVM_COV)"
    )
    assert not (tmp_path / "b").exists()


def test_c_that_is_not_the_generators_is_never_measured(tmp_path: Path) -> None:
    row = {"generated_c": "c/policy.c differs from what embedrl generates"}
    said = facts.coverage(tmp_path, {"name": "policy"}, row)
    why = "c/policy.c differs from what embedrl generates"
    assert said == f"the policy's C is not the generator's ({why}): not run on this host"
    assert coverage.check(said) == (False, f"not measured: {said}")


@pytest.mark.slow  # an export per precision, each measured
@pytest.mark.parametrize("precision", ["int8-weights", "q15", "int8"])
def test_every_gap_of_a_quantised_policy_has_its_reason(exported: Exported, precision: str) -> None:
    export = exported(SHIPPED_TD3, "--episodes", "0", "--quantize", precision)
    summary = facts.coverage(export, facts.load_export(export), {"generated_c": facts.IDENTICAL})
    assert not isinstance(summary, str), summary
    policy = _file(summary, "policy.c")
    assert policy["gaps"] and all(g["reason"] for g in policy["gaps"]), policy["gaps"]
    # int8 keeps its requantisation for scales of 1/2 or more out of line and unreached: ~14 lines
    assert policy["lines"]["covered"] >= 0.85 * policy["lines"]["count"]
    # NaN, +inf and -inf refused at the entry; an integer section never makes a non-finite result
    # (int8-weights keeps float activations: its overflow probes do)
    assert summary["probes"]["codes"]["1"] == 18 and ("2" in summary["probes"]["codes"]) == (
        precision == "int8-weights"
    )
    assert coverage.check(summary)[0]


def test_a_npy_file_as_coverage_obs_is_refused_in_one_line(tmp_path: Path) -> None:
    """A ``.npy`` file holds a header before its rows: read as raw floats, its header would be rows."""
    obs = tmp_path / "obs.npy"
    np.save(obs, np.zeros((1, 6), dtype="<f4"))
    result = subprocess.run(
        ["make", "--no-print-directory", "-C", str(RUNTIME_C), "coverage", f"POLICY_DIR={tmp_path}",
         f"COVERAGE_OBS={obs}", f"BUILD_DIR={tmp_path / 'b'}", f"PYTHON={sys.executable}"],
        capture_output=True, text=True,
    )  # fmt: skip
    assert result.returncode == 2
    assert result.stderr.splitlines()[0] == (
        f"COVERAGE_OBS {obs} is a .npy file (a header, then the rows): give raw float32 rows, e.g. "
        "numpy.load(FILE).astype('float32').tofile('obs.f32')"
    )
    assert not (tmp_path / "b").exists()
