"""MISRA C:2012 on the firmware node as deployed (cppcheck's addon, Debian's cppcheck from ``make deps``):
every finding explained by the deviation log, for every precision; a new violation fails."""

from __future__ import annotations

import shutil
from pathlib import Path

import pytest

from embedrl.hil import misra
from embedrl.hil.misra import Deviation, Finding
from tests.conftest import Exported, marks_its_users
from tests.hil.conftest import SHIPPED_TD3


@pytest.fixture(scope="module")
@marks_its_users("slow")  # four exports, cppcheck's MISRA addon over each deployed node
def exports(exported: Exported) -> dict[str, Path]:
    out = {}
    for precision in ("float32", "int8-weights", "q15", "int8"):
        quantize = [] if precision == "float32" else ["--quantize", precision]
        out[precision] = exported(SHIPPED_TD3, "--episodes", "0", *quantize)
    return out


@pytest.mark.parametrize("precision", ["float32", "int8-weights", "q15", "int8"])
def test_every_finding_on_the_deployed_node_is_explained(exports: dict[str, Path], precision: str) -> None:
    result = misra.check(exports[precision])
    assert result.unexplained == []
    files = {f.file for f in result.findings}
    assert {"c/policy.c", "runtime_c/node/node.c", "runtime_c/cortex_m/slcan.c", "can/policy_dbc.c"} <= files
    summary = result.to_json()
    assert summary["findings"] == len(result.findings) and "Cppcheck 2" in summary["tool"]
    assert all(d["why"] for d in summary["deviations"])
    assert summary["precision"] == precision and "c/policy_host.c" not in files  # host-only: not deployed
    counted = [d for d in summary["deviations"] if d["count"] is not None]
    assert counted and all(d["found"] == d["count"] for d in counted)


def test_a_new_violation_in_the_generated_code_fails(exports: dict[str, Path], tmp_path: Path) -> None:
    changed = tmp_path / "export"
    shutil.copytree(exports["float32"], changed)
    policy = changed / "c" / "policy.c"
    policy.write_text(
        policy.read_text() + "\nint policy_extra(int x)\n{\n    goto done;\ndone:\n    return x;\n}\n"
    )
    problems = misra.check(changed).unexplained
    assert any(p.startswith("c/policy.c:") and "15.1 has no deviation" in p for p in problems), problems


def test_counted_deviations_catch_one_more_and_one_fewer() -> None:
    log = [
        Deviation("15.5", ("runtime_c/*",), "guard clauses", 2),
        Deviation("8.9", ("c/*",), "tables", None),
    ]
    two = [Finding("15.5", "runtime_c/node/node.c", 10), Finding("15.5", "runtime_c/node/e2e.c", 4)]
    tables = [Finding("8.9", "c/policy.c", n) for n in range(7)]  # generated: any number
    assert misra.unexplained([*two, *tables], log) == []
    three = [*two, Finding("15.5", "runtime_c/cortex_m/slcan.c", 3)]
    assert misra.unexplained(three, log) == [
        "15.5 in runtime_c/*: 3 findings, the log says 2 (a new violation)"
    ]
    assert "fixed" in misra.unexplained(two[:1], log)[0]
    misplaced = [*two, Finding("8.9", "runtime_c/node/node.c", 3)]  # covered in c/, not in runtime_c/
    assert misra.unexplained(misplaced, log) == ["runtime_c/node/node.c:3: 8.9 has no deviation"]


def test_a_count_per_precision_holds_for_that_precision() -> None:
    log = [Deviation("10.1", ("c/*",), "(R) requantisation", {"int8": 2})]
    two = [Finding("10.1", "c/policy.c", 3), Finding("10.1", "c/policy.c", 9)]
    assert misra.unexplained(two, log, "int8") == []
    assert misra.unexplained(two, log, "q15") == [
        "10.1 in c/* (q15): 2 findings, the log says 0 (a new violation)"
    ]
    assert "fixed" in misra.unexplained(two[:1], log, "int8")[0]


def test_the_log_names_real_rules_with_reasons_and_counts() -> None:
    """Hand-written files: one count. Generated files: a count per precision, except an advisory rule's or
    cantools' codec's (third-party code whose findings grow with the interface's signals)."""
    for d in misra.load_deviations():
        assert d.why and d.files, d
        assert d.rule.replace(".", "").isdigit() or d.rule.isidentifier(), d.rule
        generated = all(p.startswith(misra.GENERATED_PREFIXES) for p in d.files)
        if not generated:
            assert isinstance(d.count, int), f"{d.rule} {d.files}: a hand-written file's entry needs a count"
        elif d.count is None:
            third_party = set(d.files) <= set(misra.THIRD_PARTY)
            assert d.category == "advisory" or third_party, f"{d.rule} {d.files}: required, needs a count"
        else:
            assert isinstance(d.count, dict) and set(d.count) <= set(misra.PRECISIONS), d


def test_our_generated_files_need_no_uncounted_required_deviation() -> None:
    ours = [
        d
        for d in misra.load_deviations()
        if any(f.startswith(misra.GENERATED_PREFIXES) and f not in misra.THIRD_PARTY for f in d.files)
    ]
    assert ours and all(d.count is not None or d.category == "advisory" for d in ours)
    assert not any(d.count is None and d.category == "required" for d in ours)


def test_every_misra_deviation_names_its_rules_category_and_one_rule_has_one() -> None:
    """(A) advisory or (R) required opens each entry of a MISRA rule (the page's category column reads it);
    cppcheck's own checks have none."""
    categories: dict[str, set[str | None]] = {}
    for d in misra.load_deviations():
        categories.setdefault(d.rule, set()).add(d.category)
    for rule, found in categories.items():
        if rule[0].isdigit():
            assert len(found) == 1 and None not in found, (rule, found)
        else:
            assert found == {None}, rule
    assert categories["8.9"] == {"advisory"} and categories["10.1"] == {"required"}
