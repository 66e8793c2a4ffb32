"""Coverage of the node in a HIL run (``embedrl hil run --coverage``): the instrumented C node runs in the
sandbox, each of its processes that exits writes its profile, and the report merges it with the C tests' and
the verification vectors' profiles, naming the sources; refusals in one line."""

from __future__ import annotations

import os
import re
import shutil
import subprocess
import sys
from pathlib import Path
from typing import Any

import pytest

from embedrl.common import sha256, write_json
from embedrl.export import chain
from embedrl.hil import coverage as recorded
from embedrl.hil.errors import HilError
from embedrl.hil.options import RunOptions
from embedrl.hil.run import add_to_chain, run
from embedrl.hil.sandbox import Guest
from embedrl.hil.signoff import conditions, coverage, facts, sections
from tests.conftest import Exported
from tests.hil.conftest import SHIPPED_TD3

GENERATED = {"generated_c": facts.IDENTICAL}
FAULTS = ("kill-restart@0:3", "link-down-up@0:8")
"""The first node process killed (SIGKILL: no profile), the second through a link that goes down and up
(main.c's re-open: code only a HIL run reaches), then stopped by the harness (SIGTERM: its profile)."""


@pytest.fixture(scope="module")
def fault_run(guest: Guest, exported: Exported, tmp_path_factory: pytest.TempPathFactory) -> dict[str, Any]:
    """One episode of the shipped TD3 with coverage and two faults, its report written outside the export
    and put in the bundle as ``hil run --json`` does; both coverage summaries (the C tests and vectors alone,
    and merged with the run's profile)."""
    export = tmp_path_factory.mktemp("covered") / "export"
    shutil.copytree(exported(SHIPPED_TD3, "--episodes", "0"), export)
    report = tmp_path_factory.mktemp("report") / "hil.json"
    options = RunOptions(
        export, episodes=1, inject=FAULTS, allow_faults=True, coverage=recorded.folder_of(report)
    )
    data = run(options, guest)
    write_json(data, report)
    assert add_to_chain(export, report, data)
    place = export / "hil" / "hil.json"
    alone = facts.coverage(export, facts.load_export(export), GENERATED)
    merged = facts.coverage(export, facts.load_export(export), GENERATED, [(place, "hil/hil.json", data)])
    assert not isinstance(alone, str) and not isinstance(merged, str), (alone, merged)
    return {"data": data, "export": export, "alone": alone, "merged": merged}


def _calls(summary: dict[str, Any], name: str) -> dict[str, int]:
    return next(f["calls"] for f in summary["files"] if f["file"] == name)


def test_a_fault_run_keeps_the_profile_of_each_node_process_that_exits(fault_run: dict[str, Any]) -> None:
    data, export = fault_run["data"], fault_run["export"]
    assert data["verdict"]["passed"] and data["faults"] == 0
    record = data["coverage"]
    # the killed process left an empty profile (left out); the restarted one wrote its own when stopped
    assert len(record["profiles"]) == 1 and len(record["unreadable"]) == 1
    assert record["folder"] == "hil.coverage"
    travelled = export / "hil" / "hil.coverage"  # the bundle holds the report's coverage folder too
    assert sha256(travelled / "policy_node") == record["binary"]["sha256"]
    assert sha256(travelled / record["profiles"][0]["file"]) == record["profiles"][0]["sha256"]


def test_the_merged_profile_counts_what_only_the_hil_run_reached(fault_run: dict[str, Any]) -> None:
    alone, merged = fault_run["alone"], fault_run["merged"]
    assert {"main.c", "transport_socketcan.c"}.isdisjoint(f["file"] for f in alone["files"])
    main = _calls(merged, "main.c")
    assert main["main"] == 1 and main["on_signal"] == 1  # stopped by SIGTERM, its profile written at exit
    assert main["reopen"] == 1  # the link that went down and up
    assert _calls(merged, "transport_socketcan.c")["transport_recv"] > 0
    # the node's and the policy's functions ran in the sandbox too: their counts grow by the run's steps
    steps = fault_run["data"]["steps"]
    grown = _calls(merged, "node.c")["complete_observation"] - _calls(alone, "node.c")["complete_observation"]
    assert 0 < grown <= steps
    assert _calls(merged, "policy.c")["policy_step"] > _calls(alone, "policy.c")["policy_step"]
    for name in ("policy.c", "node.c", "e2e.c", "policy_io.c", "slcan.c"):  # shown once each, same gaps
        rows = [f for f in merged["files"] if f["file"] == name]
        assert len(rows) == 1 and len(rows[0]["gaps"]) == len(
            next(f for f in alone["files"] if f["file"] == name)["gaps"]
        )


def test_the_report_names_the_hil_run_among_the_sources_it_merged(fault_run: dict[str, Any]) -> None:
    passed, detail = coverage.check(fault_run["merged"])
    assert passed and detail.endswith(
        "merged from the verification vectors, the C tests and HIL run hil/hil.json (1 node process "
        "profile(s); 1 empty, its process killed)"
    )
    assert coverage.check(fault_run["alone"])[1].endswith("the C tests (no HIL run with coverage)")
    page = sections.coverage({"coverage": fault_run["merged"]})
    assert 'data-key="coverage-sources">Profiles merged from the verification vectors' in page
    assert "HIL run hil/hil.json" in page


def test_the_measurement_conditions_list_the_coverage_builds(fault_run: dict[str, Any]) -> None:
    export = facts.load_export(fault_run["export"])
    recorded_build = fault_run["data"]["coverage"]["compiler"]
    assert recorded_build["command"].startswith("clang-19 -std=c99 -O0 -g -fprofile-instr-generate ")
    assert "-fcoverage-mcdc" in recorded_build["command"]
    assert recorded_build["version"].startswith("Debian clang version 19")
    merged = conditions.measurement_conditions(export, [], "cppcheck", fault_run["merged"])
    rows = {r["target"]: r for r in merged["compilers"]}
    unit = rows["host, coverage: verification vectors and C tests"]
    hil = rows["host, coverage: the node of HIL run hil/hil.json"]
    assert (unit["command"], unit["version"]) == (hil["command"], hil["version"]) == (
        recorded_build["command"], recorded_build["version"])  # fmt: skip
    alone = conditions.measurement_conditions(export, [], "cppcheck", fault_run["alone"])
    assert [r["target"] for r in alone["compilers"]] == ["host", unit["target"]]  # no HIL run merged
    page = sections.conditions({"conditions": merged})
    assert f'data-key="compiler-coverage-hil-0">{recorded_build["version"]}' in page
    without = {
        **fault_run["merged"],
        "sources": [{**s, "compiler": None} for s in fault_run["merged"]["sources"]],
    }
    page = sections.conditions({"conditions": conditions.measurement_conditions(export, [], "c", without)})
    assert 'data-key="compiler-coverage-hil-0">not recorded (run it again with --coverage)' in page


def test_verify_chain_names_a_changed_or_missing_coverage_file(
    fault_run: dict[str, Any], tmp_path: Path
) -> None:
    copy = tmp_path / "copy"
    shutil.copytree(fault_run["export"], copy)
    assert all(c.ok for c in chain.verify(copy))
    profile = next((copy / "hil" / "hil.coverage").glob("*.profraw"))
    recorded = sha256(profile)
    profile.write_bytes(profile.read_bytes() + b"x")
    said = f"hil/hil.json records hil.coverage/{profile.name} (sha256 {recorded[:12]}...), which "
    now = sha256(profile)
    assert [c.detail for c in chain.verify(copy) if not c.ok] == [f"{said}changed (sha256 {now[:12]}...)"]
    profile.unlink()
    assert [c.detail for c in chain.verify(copy) if not c.ok] == [f"{said}is missing"]


def test_a_coverage_record_naming_a_folder_elsewhere_is_refused() -> None:
    entry = {"file": "policy_node", "sha256": "0" * 64}
    with pytest.raises(ValueError, match=re.escape("its coverage folder '../x' is not one name beside the")):
        chain.recorded_coverage({"coverage": {"folder": "../x", "binary": entry, "profiles": []}})
    with pytest.raises(ValueError, match="is not an object of a file name and its sha256"):
        outside = {**entry, "file": "../p"}
        chain.recorded_coverage({"coverage": {"folder": "x", "binary": outside, "profiles": []}})
    assert chain.recorded_coverage({"coverage": {"folder": "x", "binary": entry, "profiles": [entry]}}) == {
        "x/policy_node": "0" * 64
    }


def test_a_hil_report_without_its_coverage_is_named_and_a_changed_profile_fails(tmp_path: Path) -> None:
    report = tmp_path / "hil.json"
    with pytest.raises(HilError, match=r"^hil.json: a run without coverage \(embedrl hil run --coverage\)$"):
        recorded.sources(report, {"coverage": None})
    with pytest.raises(HilError, match=r"^hil.json: a firmware node run \(coverage measures the C node"):
        recorded.sources(report, {"coverage": None, "node": "firmware"})
    folder = recorded.folder_of(report)
    folder.mkdir()
    (folder / "policy_node").write_bytes(b"binary")
    (folder / "node-7.profraw").write_bytes(b"profile")
    binary, profile = folder / "policy_node", folder / "node-7.profraw"
    record = {"folder": folder.name, "binary": {"file": binary.name, "sha256": sha256(binary)},
              "profiles": [{"file": profile.name, "sha256": sha256(profile)}]}  # fmt: skip
    assert recorded.sources(report, {"coverage": record}) == (binary, [profile])
    profile.write_bytes(b"edited")
    with pytest.raises(HilError, match=r"its coverage file node-7\.profraw changed since the run"):
        recorded.sources(report, {"coverage": record})
    profile.unlink()
    with pytest.raises(HilError, match=re.escape(f"its coverage file node-7.profraw is not in {folder}")):
        recorded.sources(report, {"coverage": record})
    unit = [{"source": s, "profiles": 1} for s in coverage.UNIT_SOURCES]
    without = {"report": "a.json", "why": "a.json: a run without coverage", "failed": False}
    summary: dict[str, Any] = {"files": [], "sources": unit, "hil_not_merged": [without]}
    assert coverage.check(summary) == (
        True,
        "; 0 gap(s), each with its reason; merged from the verification vectors, the C tests (no HIL run "
        "with coverage); not merged: a.json: a run without coverage",
    )
    summary["hil_not_merged"].append({"report": "b.json", "why": "b.json: its coverage file x changed",
                                      "failed": True})  # fmt: skip
    passed, detail = coverage.check(summary)
    assert not passed and detail.startswith("b.json: its coverage file x changed; merged from")


def _hil_run(*flags: str, path: str | None = None) -> subprocess.CompletedProcess[str]:
    env = {**os.environ, **({"PATH": path} if path is not None else {})}
    return subprocess.run([sys.executable, "-m", "embedrl", "hil", "run", *flags], capture_output=True,
                          text=True, env=env)  # fmt: skip


def test_coverage_without_its_tools_or_without_a_report_is_refused_in_one_line(tmp_path: Path) -> None:
    json = tmp_path / "hil.json"
    result = _hil_run("--export-dir", str(tmp_path), "--coverage", "--json", str(json), path=str(tmp_path))
    assert result.returncode == 2 and result.stderr.splitlines() == [
        "error: --coverage needs clang-19 and llvm-profdata-19, not found on PATH (Debian: apt-get install "
        "clang-19 llvm-19)"
    ]
    result = _hil_run("--export-dir", str(tmp_path), "--coverage")
    assert result.returncode == 2 and result.stderr.splitlines() == [
        "error: --coverage keeps the node's profiles beside the report: give --json REPORT.json"
    ]
    (tmp_path / "hil.coverage").mkdir()
    (tmp_path / "hil.coverage" / "notes.txt").write_bytes(b"")
    result = _hil_run("--export-dir", str(tmp_path), "--coverage", "--json", str(json))
    assert result.returncode == 2 and result.stderr.splitlines() == [
        f"error: --coverage: {tmp_path / 'hil.coverage'} holds other files than a coverage run's (*.profraw, "
        "policy_node); move them"
    ]
    assert sorted(p.name for p in tmp_path.iterdir()) == ["hil.coverage"]
