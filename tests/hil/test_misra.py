"""MISRA C:2012 on the firmware node as deployed (cppcheck's addon, Debian's cppcheck from ``make deps``):
every finding explained by the deviation log, for every precision; a new violation fails."""

from __future__ import annotations

import shutil
from pathlib import Path

import pytest

from embedrl.export import build
from embedrl.export.target import TARGETS
from embedrl.hil import misra
from embedrl.hil.misra import Deviation, Finding
from tests.conftest import Exported, marks_its_users
from tests.hil.conftest import SHIPPED_TD3

EVERY_TARGET = {name: build.compiler(name)["command"] for name in TARGETS}
"""Each Cortex-M target's compiler command (``make -C runtime_c flags TARGET=...``), as exports record it."""


@pytest.fixture(scope="module")
@marks_its_users("slow")  # four exports, cppcheck's MISRA addon over each deployed node
def exports(exported: Exported) -> dict[str, Path]:
    out = {}
    for precision in ("float32", "int8-weights", "q15", "int8"):
        quantize = [] if precision == "float32" else ["--quantize", precision]
        out[precision] = exported(SHIPPED_TD3, "--episodes", "0", *quantize)
    return out


@pytest.fixture(scope="module")
@marks_its_users("slow", "qemu")  # the export runs the M4 firmware on QEMU
def target_export(exported: Exported) -> Path:
    """The shipped TD3 exported for the M4 (as ``make demo`` exports it): its report records the target."""
    return exported(SHIPPED_TD3, "--episodes", "0", "--target", "cortex-m4")


@pytest.mark.parametrize("precision", ["float32", "int8-weights", "q15", "int8"])
def test_every_finding_on_the_deployed_node_is_explained(exports: dict[str, Path], precision: str) -> None:
    """In the host's configuration and every Cortex-M target's: the log holds whatever --target builds."""
    result = misra.check(exports[precision], targets=EVERY_TARGET)
    assert [c.name for c in result.configurations] == ["host", *TARGETS]
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


def test_a_violation_only_in_the_cortex_m_forms_is_reported_for_an_export_with_a_target(
    target_export: Path, tmp_path: Path
) -> None:
    """A goto in the VLDM form of the float dot products (compiled on a Cortex-M core with a single-precision
    FPU, GNU C): the host's configuration never compiles it, the export's cortex-m4 does."""
    changed = tmp_path / "export"
    shutil.copytree(target_export, changed)
    _plant_goto(changed / "c" / "policy.c", "    #if POLICY_VLDM\n")
    result = misra.check(changed)
    assert [c.name for c in result.configurations] == ["host", "cortex-m4"]
    gotos = [f for f in result.findings if f.rule == "15.1"]
    assert [(f.file, f.configurations) for f in gotos] == [("c/policy.c", ("cortex-m4",))], gotos
    assert any(p.startswith("c/policy.c:") and "15.1 has no deviation" in p for p in result.unexplained)
    host, m4 = result.to_json()["configurations"]
    assert m4["findings"] > host["findings"] and "-mcpu=cortex-m4" in m4["compiler"]
    assert misra.check(changed, targets={}).unexplained == []  # the host's configuration alone misses it


@pytest.mark.parametrize(
    ("precision", "branch", "configurations"),
    [
        ("float32", "    #elif POLICY_DOT_PRODUCTS\n", ("cortex-m3",)),  # C dot products: no FPU (M4: VLDM)
        ("int8", "    #if POLICY_DSP\n", ("cortex-m4",)),  # the DSP loop (not the M3's: no DSP extension)
    ],
)
def test_a_violation_in_one_target_form_is_reported_in_the_configurations_that_compile_it(
    exports: dict[str, Path], tmp_path: Path, precision: str, branch: str, configurations: tuple[str, ...]
) -> None:
    """Against the host's and two targets' configurations, one of which compiles another form."""
    changed = tmp_path / "export"
    shutil.copytree(exports[precision], changed)
    _plant_goto(changed / "c" / "policy.c", branch)
    targets = {name: EVERY_TARGET[name] for name in ("cortex-m3", "cortex-m4")}
    gotos = [f for f in misra.check(changed, targets=targets).findings if f.rule == "15.1"]
    assert [(f.file, f.configurations) for f in gotos] == [("c/policy.c", configurations)], gotos


def test_a_program_is_analysed_again_only_when_a_file_cppcheck_reads_changed(
    exports: dict[str, Path], tmp_path: Path, monkeypatch: pytest.MonkeyPatch
) -> None:
    first = misra.check(exports["q15"])

    def analyse_again(*args: object) -> None:
        raise AssertionError("cppcheck ran again")

    monkeypatch.setattr(misra, "_cppcheck_once", analyse_again)
    moved = tmp_path / "the same export"
    shutil.copytree(exports["q15"], moved)
    assert misra.check(moved).findings == first.findings  # same files elsewhere: no new analysis
    header = moved / "can" / "policy_io.h"
    header.write_text(header.read_text() + "\n/* changed */\n")
    with pytest.raises(AssertionError, match="cppcheck ran again"):
        misra.check(moved)


def _plant_goto(policy: Path, branch: str) -> None:
    """A goto (rule 15.1) as the first statement of the first ``branch`` line's block in ``policy``."""
    text = policy.read_text()
    assert branch in text, branch
    policy.write_text(text.replace(branch, branch + "    goto planted;\nplanted:\n", 1))


def test_a_targets_configuration_takes_its_compilers_predefined_macros() -> None:
    tested = {"__ARM_FEATURE_SIMD32", "__x86_64__", "POLICY_VLDM"}  # as the sources test them
    m4, m3, m7 = (misra.target_configuration(n, EVERY_TARGET[n], tested) for n in ("cortex-m4", "cortex-m3",
                                                                                 "cortex-m7"))  # fmt: skip
    for c in (m4, m3, m7):
        assert {"__ARM_ARCH_PROFILE=77", "__ARM_ARCH=7"} <= set(c.defines) and c.compiler, c
        assert any(d.startswith("__GNUC__=") for d in c.defines), c
        assert not any(d.startswith(("__x86_64__", "POLICY_VLDM")) for d in c.defines), c
    assert {"__ARM_FP=4", "__ARM_FEATURE_DSP=1", "__ARM_FEATURE_SIMD32=1"} <= set(m4.defines)
    assert {"__ARM_FP=14", "__ARM_FEATURE_DSP=1"} <= set(m7.defines)  # fpv5-d16: single and double
    assert not any(d.startswith(("__ARM_FP=", "__ARM_FEATURE_DSP")) for d in m3.defines)  # no FPU, no DSP


def test_the_macros_the_sources_test_are_read_from_their_conditionals(tmp_path: Path) -> None:
    source = tmp_path / "a.c"
    source.write_text(
        "#if defined(__ARM_FP) && \\\n    (__ARM_FEATURE_DSP == 1) /* NOT_THIS */\n#endif\n"
        "#ifdef __GNUC__\n#elif X_Y\n#endif\nint __ARM_NOT_TESTED;\n"
    )
    assert misra.tested_macros([source]) == {"defined", "__ARM_FP", "__ARM_FEATURE_DSP", "__GNUC__", "X_Y"}


def test_the_report_shows_the_configurations_and_where_a_finding_occurs() -> None:
    from embedrl.hil.signoff import sections

    host = misra.Configuration("host", misra.HOST_DEFINES)
    m4 = misra.Configuration(
        "cortex-m4", ("__ARM_ARCH_PROFILE=77", "__ARM_FP=4"), "arm-none-eabi-gcc -mcpu=cortex-m4"
    )
    findings = [
        Finding("8.9", "c/policy.c", 7, ("host", "cortex-m4")),
        Finding("8.9", "c/policy.c", 12, ("cortex-m4",)),
    ]
    log = [Deviation("8.9", ("c/*",), "(A) tables", None)]
    summary = misra.Result(findings, log, [], "float32", (host, m4)).to_json()
    assert [(c["name"], c["findings"]) for c in summary["configurations"]] == [("host", 1), ("cortex-m4", 2)]
    html = sections.coding_standard({"coding_standard": summary, "warnings": "cc -Wall"})
    assert 'data-key="misra-configurations">host, cortex-m4<' in html
    assert "-D__ARM_ARCH_PROFILE=77 -D__ARM_FP=4" in html and "arm-none-eabi-gcc -mcpu=cortex-m4" in html
    assert "c/policy.c:12 (cortex-m4 only)" in html and "c/policy.c:7</code>" in html


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
