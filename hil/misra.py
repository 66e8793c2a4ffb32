"""The coding standard of the deployed program: the firmware node (``runtime_c/node``, the Cortex-M
platform files), the CAN code generated for the policy's interface and the generated policy, checked
against MISRA C:2012 with cppcheck's MISRA addon (Debian's cppcheck; rule numbers only, since the rule
texts are not distributed), as one program so that a macro or function used in another file counts.

Every finding must be explained by an entry of the deviation log (``runtime_c/misra_deviations.toml``):
a rule (or a cppcheck check id), the files it covers, why, and for hand-written files the exact number of
findings, so that a new violation, or a fixed one left in the log, fails the check. Generated files take
no count: their findings scale with the network and the interface, the entry covers the construct.

The host node's platform files (``node/main.c``, SocketCAN, POSIX clock) are a test harness on Linux, not
deployed, and are not checked.
"""

from __future__ import annotations

import fnmatch
import shutil
import subprocess
import tomllib
from collections import Counter
from dataclasses import dataclass
from pathlib import Path
from typing import Any

from embedrl.common import owned_temporary_folder
from embedrl.export.build import RUNTIME_C
from embedrl.export.contract.interface_file import load_interface
from embedrl.export.contract.sources import folder, write
from embedrl.hil.errors import HilError
from embedrl.train.interface import INTERFACE_FILE

DEVIATIONS = RUNTIME_C / "misra_deviations.toml"
FIRMWARE_SOURCES = (
    "node/node.c", "node/e2e.c", "cortex_m/node_main.c", "cortex_m/transport_uart.c", "cortex_m/slcan.c",
    "cortex_m/timer.c", "cortex_m/clock_sim.c", "cortex_m/startup.c",
)  # fmt: skip
"""runtime_c's files of the firmware node (runtime_c/Makefile's FW_NODE_SRCS with its default clock,
NODE_CLOCK=sim, and STARTUP)."""
MISRA_BOARD = "stm32f4"
"""The board file checked with the node: the default target's (cortex-m4, the STM32F405)."""
CPPCHECK = ("cppcheck", "--addon=misra", "--std=c99", "--platform=arm32-wchar_t4", "-D__ARM_FP=4", "-q")
"""A 32-bit Arm target with an FPU (the start-up code's FPU branch is analysed too)."""
GENERATED_PREFIXES = ("c/", "can/")
"""Labels of generated files: their deviations take no count."""


@dataclass(frozen=True)
class Finding:
    rule: str
    """``misra-c2012-R.N`` as ``R.N``, or a cppcheck check id (e.g. ``comparePointers``)."""
    file: str
    """``c/...`` (the generated policy), ``can/...`` (the generated CAN code) or ``runtime_c/...``."""
    line: int


@dataclass(frozen=True)
class Deviation:
    rule: str
    files: tuple[str, ...]
    why: str
    """Opens with the rule's category in MISRA C:2012, ``(A)`` advisory, ``(R)`` required or ``(M)``
    mandatory; a cppcheck check of its own has none."""
    count: int | None

    @property
    def category(self) -> str | None:
        return next((name for mark, name in CATEGORIES.items() if self.why.startswith(mark)), None)


CATEGORIES = {"(A)": "advisory", "(R)": "required", "(M)": "mandatory"}
"""MISRA C:2012's guideline categories as the deviation log marks them: advisory rules may be deviated
with a recorded reason, required ones only with a formal deviation, mandatory ones never."""


@dataclass(frozen=True)
class Result:
    findings: list[Finding]
    deviations: list[Deviation]
    unexplained: list[str]
    """One line per finding without a deviation, or per count that no longer holds."""

    def to_json(self) -> dict[str, Any]:
        per_rule = Counter((f.rule, f.file) for f in self.findings)
        return {
            "tool": cppcheck_version(),
            "checked": sorted({f.file for f in self.findings} | set(_checked_labels())),
            "findings": len(self.findings),
            "by_rule_and_file": [
                {"rule": rule, "file": file, "count": n} for (rule, file), n in sorted(per_rule.items())
            ],
            "at": [{"rule": f.rule, "file": f.file, "line": f.line} for f in self.findings],
            "categories": {d.rule: d.category for d in self.deviations if d.category},
            "deviations": [
                {
                    "rule": d.rule,
                    "files": list(d.files),
                    "why": d.why,
                    "count": d.count,
                    "category": d.category,
                }
                for d in self.deviations
            ],
            "unexplained": self.unexplained,
        }


def load_deviations(path: Path = DEVIATIONS) -> list[Deviation]:
    entries = tomllib.loads(path.read_text()).get("deviation", [])
    return [
        Deviation(str(e["rule"]), tuple(e["files"]), str(e["why"]).strip(), e.get("count")) for e in entries
    ]


def check(export_dir: Path, deviations: list[Deviation] | None = None) -> Result:
    """The firmware node with the export's policy and the CAN code of its interface, against the log."""
    deviations = load_deviations() if deviations is None else deviations
    findings = run_cppcheck(export_dir)
    return Result(findings, deviations, unexplained(findings, deviations))


def unexplained(findings: list[Finding], deviations: list[Deviation]) -> list[str]:
    """Findings no deviation covers, and counted deviations whose count is not what was found."""
    problems = []
    covered: Counter[tuple[int, str]] = Counter()
    for f in findings:
        match = next((k for k, d in enumerate(deviations) if d.rule == f.rule and _covers(d, f.file)), None)
        if match is None:
            problems.append(f"{f.file}:{f.line}: {f.rule} has no deviation")
        else:
            covered[(match, f.file)] += 1
    for k, d in enumerate(deviations):
        if d.count is None:
            continue
        found = sum(n for (index, _), n in covered.items() if index == k)
        if found != d.count:
            change = "a new violation" if found > d.count else "fixed: lower the count or drop the entry"
            problems.append(
                f"{d.rule} in {', '.join(d.files)}: {found} findings, the log says {d.count} ({change})"
            )
    return problems


def _covers(deviation: Deviation, label: str) -> bool:
    return any(fnmatch.fnmatchcase(label, pattern) for pattern in deviation.files)


def _checked_labels() -> list[str]:
    return [f"runtime_c/{s}" for s in FIRMWARE_SOURCES]


def run_cppcheck(export_dir: Path) -> list[Finding]:
    if shutil.which("cppcheck") is None:
        raise HilError("cppcheck is not installed: run `make deps` (Debian's cppcheck)")
    with owned_temporary_folder("embedrl-misra-") as tmp:
        can = export_dir / folder(fd=False)  # the classic CAN code the firmware node is built from
        if not can.is_dir():  # exported before exports carried it: the same generator's
            can = Path(tmp) / "can"
            write(load_interface(export_dir / INTERFACE_FILE), can)
        sources = [
            *(RUNTIME_C / s for s in FIRMWARE_SOURCES),
            *sorted(can.glob("*.c")),
            *sorted((export_dir / "c").glob("*.c")),
        ]
        board = RUNTIME_C / "cortex_m" / "boards" / MISRA_BOARD
        includes = [RUNTIME_C / "node", RUNTIME_C / "cortex_m", board, can, export_dir / "c"]
        result = subprocess.run(
            [*CPPCHECK, "--template={file}|{line}|{id}", *(f"-I{i}" for i in includes), *map(str, sources)],
            capture_output=True, text=True,
        )  # fmt: skip
        roots = {"runtime_c/": RUNTIME_C.resolve(), "can/": can.resolve(), "c/": (export_dir / "c").resolve()}
        findings = []
        for line in result.stderr.splitlines():
            parts = line.rsplit("|", 2)
            if len(parts) != 3 or not parts[1].isdigit():
                continue
            path, number, check_id = parts
            findings.append(Finding(_rule(check_id), _label(Path(path).resolve(), roots), int(number)))
    if result.returncode != 0:
        raise HilError(f"cppcheck failed (status {result.returncode}): {result.stderr.strip()[-300:]}")
    return sorted(findings, key=lambda f: (f.file, f.line, f.rule))


def _rule(check_id: str) -> str:
    return check_id.removeprefix("misra-c2012-")


def _label(path: Path, roots: dict[str, Path]) -> str:
    for prefix, root in roots.items():
        if path.is_relative_to(root):
            return prefix + str(path.relative_to(root))
    return str(path)


def cppcheck_version() -> str:
    try:
        return subprocess.run(["cppcheck", "--version"], capture_output=True, text=True).stdout.strip()
    except OSError:
        return "cppcheck not installed"
