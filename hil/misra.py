"""The coding standard of the deployed program: the firmware node (``runtime_c/node``, the Cortex-M
platform files), the CAN code generated for the policy's interface and the generated policy, checked
against MISRA C:2012 with cppcheck's MISRA addon (Debian's cppcheck; rule numbers only, since the rule
texts are not distributed), as one program so that a macro or function used in another file counts.

Every finding must be explained by an entry of the deviation log (``runtime_c/misra_deviations.toml``):
a rule (or a cppcheck check id), the files it covers, why, and the exact number of findings, so that a new
violation, or a fixed one left in the log, fails the check. Hand-written files name one number. A required
rule in generated files names one number per precision of the policy (``count = {int8 = 3}``, none
for a precision not named): such findings come from the fixed helpers a precision brings (the requantisation
of int8), not from the network's size. Only an advisory rule's entry for generated files may go
without a count, when its findings scale with the network or the interface (one per weight table, per
early return, per macro of the header); its reason says so.

The host node's platform files (``node/main.c``, SocketCAN, POSIX clock) are a test harness on Linux, not
deployed, and are not checked.

The program is analysed in each configuration it is built for (cppcheck checks one set of ``-D`` macros
per run): ``host``, the standard C forms a compiler without GNU C and Cortex-M macros compiles, and for an
export made with ``--target`` each Cortex-M target's, with the macros its compiler predefines for the
target's flags (``arm-none-eabi-gcc ... -dM -E``): the dot products, the VLDM form and int8's DSP loop the
firmware runs. A finding is reported once, with the configurations it occurs in. cppcheck's findings for a
program and configuration are kept for the life of the process (:data:`_ANALYSED`), keyed by the content of
every file it reads: a report that checks the export a test or script checked before runs no cppcheck again.
"""

from __future__ import annotations

import fnmatch
import functools
import hashlib
import json
import re
import shlex
import shutil
import subprocess
import tomllib
from collections import Counter
from collections.abc import Iterable
from dataclasses import dataclass
from pathlib import Path
from typing import Any

from embedrl.common import owned_temporary_folder
from embedrl.export.build import RUNTIME_C
from embedrl.export.codegen import HOST_SUFFIX
from embedrl.export.contract.interface_file import load_interface
from embedrl.export.contract.sources import folder, write
from embedrl.export.target import TARGETS
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
"""The board file checked with the node, in every configuration: the default target's (cortex-m4, the
STM32F405). Each board file would bring its own findings (its registers, rule 11.4; its unused macros, 2.5),
which the log's hand-written counts, one number each, do not separate by board."""
CPPCHECK = ("cppcheck", "--addon=misra", "--std=c99", "--platform=arm32-wchar_t4", "-q")
"""A 32-bit Arm target; each configuration adds its ``-D`` macros (cppcheck then checks that one only)."""
HOST = "host"
HOST_DEFINES = ("__ARM_FP=4",)
"""The host configuration's macros: none of a compiler's (the standard C forms of the generated code) but
an FPU, so that the start-up code's FPU branch is analysed in an export without targets too."""
TARGET_MACROS = ("__ARM_ARCH_PROFILE", "__ARM_ARCH", "__GNUC__", "__ARM_FP", "__ARM_FEATURE_DSP")
"""Macros a target's configuration always takes where its compiler predefines them (the core, its FPU and
DSP extension, GNU C), besides every predefined macro the analysed sources test."""
CONDITIONAL = re.compile(r"^\s*#\s*(?:if|ifdef|ifndef|elif)\b(.*)$", re.MULTILINE)
IDENTIFIER = re.compile(r"\b[A-Za-z_]\w*\b")
GENERATED_PREFIXES = ("c/", "can/")
"""Labels of generated files: their deviations count per precision, or not at all for an advisory rule."""
THIRD_PARTY = ("can/policy_dbc.c", "can/policy_dbc.h")
"""cantools' codec, generated from the DBC by a third party's generator: its entries take no count (its
findings grow with the interface's signals)."""
PRECISIONS = ("float32", "int8", "int8-weights", "q15")
"""The precisions of a generated policy (``embedrl export --quantize``; float32 without it)."""
EXPORT_REPORT = "export_report.json"


@dataclass(frozen=True)
class Finding:
    rule: str
    """``misra-c2012-R.N`` as ``R.N``, or a cppcheck check id (e.g. ``comparePointers``)."""
    file: str
    """``c/...`` (the generated policy), ``can/...`` (the generated CAN code) or ``runtime_c/...``."""
    line: int
    configurations: tuple[str, ...] = ()
    """The configurations it occurs in (:class:`Configuration` names), in the order they were analysed."""


@dataclass(frozen=True)
class Configuration:
    """One set of macros the program is analysed with: the host's, or a Cortex-M target's."""

    name: str
    """``host`` or the target's name (``cortex-m4``)."""
    defines: tuple[str, ...]
    """``NAME=VALUE`` for cppcheck's ``-D``."""
    compiler: str | None = None
    """The compiler command whose predefined macros these are (a target's), None for the host."""


@dataclass(frozen=True)
class Deviation:
    rule: str
    files: tuple[str, ...]
    why: str
    """Opens with the rule's category in MISRA C:2012, ``(A)`` advisory, ``(R)`` required or ``(M)``
    mandatory; a cppcheck check of its own has none."""
    count: int | dict[str, int] | None
    """The findings it covers: one number (hand-written files), one per precision (a required rule in
    generated files; a precision not named has none) or None (an advisory rule in generated files)."""

    def expected(self, precision: str) -> int | None:
        """The findings this entry covers in an export of ``precision``; None: not counted."""
        if isinstance(self.count, dict):
            return self.count.get(precision, 0)
        return self.count

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
    precision: str = "float32"
    configurations: tuple[Configuration, ...] = ()

    def to_json(self) -> dict[str, Any]:
        per_rule = Counter((f.rule, f.file) for f in self.findings)
        found = covered_by(self.findings, self.deviations)
        return {
            "tool": cppcheck_version(),
            "checked": sorted({f.file for f in self.findings} | set(_checked_labels())),
            "configurations": [
                {
                    "name": c.name,
                    "defines": list(c.defines),
                    "compiler": c.compiler,
                    "findings": sum(c.name in f.configurations for f in self.findings),
                }
                for c in self.configurations
            ],
            "findings": len(self.findings),
            "by_rule_and_file": [
                {"rule": rule, "file": file, "count": n} for (rule, file), n in sorted(per_rule.items())
            ],
            "at": [
                {"rule": f.rule, "file": f.file, "line": f.line, "configurations": list(f.configurations)}
                for f in self.findings
            ],
            "categories": {d.rule: d.category for d in self.deviations if d.category},
            "precision": self.precision,
            "deviations": [
                {
                    "rule": d.rule,
                    "files": list(d.files),
                    "why": d.why,
                    "count": d.expected(self.precision),
                    "count_by_precision": d.count if isinstance(d.count, dict) else None,
                    "found": found[k],
                    "category": d.category,
                }
                for k, d in enumerate(self.deviations)
            ],
            "unexplained": self.unexplained,
        }


def load_deviations(path: Path = DEVIATIONS) -> list[Deviation]:
    entries = tomllib.loads(path.read_text()).get("deviation", [])
    return [
        Deviation(str(e["rule"]), tuple(e["files"]), str(e["why"]).strip(), _count(e.get("count"), path))
        for e in entries
    ]


def _count(value: Any, path: Path) -> int | dict[str, int] | None:
    if isinstance(value, dict):
        unknown = sorted(set(value) - set(PRECISIONS))
        if unknown:
            known = ", ".join(PRECISIONS)
            raise HilError(f"{path}: count names unknown precision(s) {unknown}; known: {known}")
        return {str(k): int(v) for k, v in value.items()}
    return None if value is None else int(value)


def _export_report(export_dir: Path) -> dict[str, Any]:
    try:
        report = json.loads((export_dir / EXPORT_REPORT).read_text())
    except (OSError, ValueError) as e:
        raise HilError(f"{export_dir} is not an export folder: no readable {EXPORT_REPORT} ({e})") from None
    if not isinstance(report, dict):
        raise HilError(f"{export_dir / EXPORT_REPORT}: not an export report (a JSON object)")
    return report


def precision_of(export_dir: Path) -> str:
    """The precision of the export's policy, from its report (float32 without --quantize)."""
    return str(_export_report(export_dir).get("quantize") or "float32")


def targets_of(export_dir: Path) -> dict[str, str]:
    """The Cortex-M targets the export was built for (``--target``), each with the compiler command its
    report records (``make -C runtime_c flags TARGET=...`` when it was exported)."""
    recorded = _export_report(export_dir).get("targets") or {}
    if not isinstance(recorded, dict):
        raise HilError(f"{export_dir / EXPORT_REPORT}: 'targets' is not an object of targets")
    commands = {}
    for name, facts in recorded.items():
        command = facts.get("compiler", {}).get("command") if isinstance(facts, dict) else None
        if name not in TARGETS:
            known = ", ".join(TARGETS)
            raise HilError(f"{export_dir / EXPORT_REPORT}: unknown target {name!r}; known: {known}")
        if not isinstance(command, str) or not command.strip():
            raise HilError(f"{export_dir / EXPORT_REPORT}: target {name!r} has no recorded compiler command")
        commands[str(name)] = command
    return commands


def check(
    export_dir: Path, deviations: list[Deviation] | None = None, targets: dict[str, str] | None = None
) -> Result:
    """The firmware node with the export's policy and the CAN code of its interface, against the log, in
    the host's configuration and each target's (``targets``: name -> compiler command; the export's own
    when None)."""
    deviations = load_deviations() if deviations is None else deviations
    precision = precision_of(export_dir)
    targets = targets_of(export_dir) if targets is None else targets
    findings, analysed = run_cppcheck(export_dir, targets)
    return Result(findings, deviations, unexplained(findings, deviations, precision), precision, analysed)


def unexplained(
    findings: list[Finding], deviations: list[Deviation], precision: str = "float32"
) -> list[str]:
    """Findings no deviation covers, and counted deviations whose count (for an export of ``precision``) is
    not what was found."""
    problems = [
        f"{f.file}:{f.line}: {f.rule} has no deviation" for f in findings if _entry(f, deviations) is None
    ]
    covered = covered_by(findings, deviations)
    for k, d in enumerate(deviations):
        expected = d.expected(precision)
        if expected is None:
            continue
        found = covered[k]
        if found != expected:
            change = "a new violation" if found > expected else "fixed: lower the count or drop the entry"
            files = ", ".join(d.files) + (f" ({precision})" if isinstance(d.count, dict) else "")
            problems.append(f"{d.rule} in {files}: {found} findings, the log says {expected} ({change})")
    return problems


def covered_by(findings: list[Finding], deviations: list[Deviation]) -> Counter[int]:
    """How many findings each deviation (by index) explains: a finding counts for the first that covers it."""
    return Counter(k for f in findings if (k := _entry(f, deviations)) is not None)


def _entry(finding: Finding, deviations: list[Deviation]) -> int | None:
    return next(
        (k for k, d in enumerate(deviations) if d.rule == finding.rule and _covers(d, finding.file)), None
    )


def _covers(deviation: Deviation, label: str) -> bool:
    return any(fnmatch.fnmatchcase(label, pattern) for pattern in deviation.files)


def _checked_labels() -> list[str]:
    return [f"runtime_c/{s}" for s in FIRMWARE_SOURCES]


def run_cppcheck(
    export_dir: Path, targets: dict[str, str] | None = None
) -> tuple[list[Finding], tuple[Configuration, ...]]:
    """cppcheck's findings over the program in the host's configuration and each of ``targets``' (name ->
    compiler command), merged: one finding per rule and place, with the configurations it occurs in."""
    if shutil.which("cppcheck") is None:
        raise HilError("cppcheck is not installed: run `make deps` (Debian's cppcheck)")
    with owned_temporary_folder("embedrl-misra-") as tmp:
        # cppcheck writes a .dump beside each file it analyses: it analyses copies, so that runs side by
        # side (and the export folder, which it must not change) never share one
        roots, sources, includes = _copy_program(export_dir, Path(tmp))
        tested = tested_macros(p for root in roots.values() for p in root.rglob("*.[ch]"))
        analysed = (
            Configuration(HOST, HOST_DEFINES),
            *(target_configuration(name, command, tested) for name, command in (targets or {}).items()),
        )
        program = _program_digest(Path(tmp), sources, includes)
        places: dict[tuple[str, str, int], list[str]] = {}
        for configuration in analysed:
            key = (program, configuration.defines)
            if key not in _ANALYSED:
                _ANALYSED[key] = _cppcheck_once(configuration, sources, includes, roots)
            for rule, label, line in _ANALYSED[key]:
                names = places.setdefault((rule, label, line), [])
                if configuration.name not in names:
                    names.append(configuration.name)
    findings = [Finding(rule, label, line, tuple(names)) for (rule, label, line), names in places.items()]
    return sorted(findings, key=lambda f: (f.file, f.line, f.rule)), analysed


_ANALYSED: dict[tuple[str, tuple[str, ...]], list[tuple[str, str, int]]] = {}
"""(program digest, configuration's macros) -> cppcheck's (rule, label, line) findings, in this process."""


def _program_digest(tmp: Path, sources: list[Path], includes: list[Path]) -> str:
    """SHA-256 of everything a cppcheck run over the copied program reads: cppcheck's version and options,
    the sources and include folders named (relative to ``tmp``) and every file under ``tmp`` with its
    content."""
    digest = hashlib.sha256(json.dumps([cppcheck_version(), CPPCHECK]).encode())
    for path in (*sources, *includes):
        digest.update(f"\0named {path.relative_to(tmp)}".encode())
    for path in sorted(p for p in tmp.rglob("*") if p.is_file()):
        digest.update(f"\0file {path.relative_to(tmp)}\0".encode())
        digest.update(path.read_bytes())
    return digest.hexdigest()


def _copy_program(export_dir: Path, tmp: Path) -> tuple[dict[str, Path], list[Path], list[Path]]:
    """runtime_c's node and Cortex-M files, the export's policy and CAN code, copied into ``tmp``: the
    label roots, the sources to analyse and the include folders."""
    runtime, c_dir, can = tmp / "runtime_c", tmp / "c", tmp / "can"
    for part in ("node", "cortex_m"):
        shutil.copytree(RUNTIME_C / part, runtime / part)
    shutil.copytree(export_dir / "c", c_dir)
    exported_can = export_dir / folder(fd=False)  # the classic CAN code the firmware node is built from
    if exported_can.is_dir():
        shutil.copytree(exported_can, can)
    else:  # exported before exports carried it: the same generator's
        write(load_interface(export_dir / INTERFACE_FILE), can)
    sources = [
        *(runtime / s for s in FIRMWARE_SOURCES),
        *sorted(can.glob("*.c")),
        *sorted(p for p in c_dir.glob("*.c") if not p.name.endswith(HOST_SUFFIX)),
    ]
    board = runtime / "cortex_m" / "boards" / MISRA_BOARD
    includes = [runtime / "node", runtime / "cortex_m", board, can, c_dir]
    roots = {"runtime_c/": runtime.resolve(), "can/": can.resolve(), "c/": c_dir.resolve()}
    return roots, sources, includes


def _cppcheck_once(
    configuration: Configuration, sources: list[Path], includes: list[Path], roots: dict[str, Path]
) -> list[tuple[str, str, int]]:
    """(rule, label, line) of each finding in one configuration."""
    result = subprocess.run(
        [*CPPCHECK, *(f"-D{d}" for d in configuration.defines), "--template={file}|{line}|{id}",
         *(f"-I{i}" for i in includes), *map(str, sources)],
        capture_output=True, text=True,
    )  # fmt: skip
    if result.returncode != 0:
        raise HilError(
            f"cppcheck failed in the {configuration.name} configuration (status {result.returncode}): "
            f"{result.stderr.strip()[-300:]}"
        )
    found = []
    for line in result.stderr.splitlines():
        parts = line.rsplit("|", 2)
        if len(parts) != 3 or not parts[1].isdigit():
            continue
        path, number, check_id = parts
        found.append((_rule(check_id), _label(Path(path).resolve(), roots), int(number)))
    return found


def tested_macros(files: Iterable[Path]) -> set[str]:
    """Every identifier a preprocessor conditional (``#if``, ``#ifdef``, ``#ifndef``, ``#elif``) of
    ``files`` tests."""
    names: set[str] = set()
    for path in files:
        text = path.read_text(errors="replace").replace("\\\n", " ")
        for condition in CONDITIONAL.findall(text):
            names.update(IDENTIFIER.findall(condition.split("/*")[0].split("//")[0]))
    return names


def target_configuration(name: str, command: str, tested: set[str]) -> Configuration:
    """The configuration of target ``name`` built by ``command`` (its compiler and flags): the macros of
    :data:`TARGET_MACROS` and those of ``tested`` that the compiler predefines for these flags."""
    predefined = predefined_macros(command)
    wanted = sorted((set(TARGET_MACROS) | tested) & set(predefined))
    return Configuration(name, tuple(f"{m}={predefined[m]}" for m in wanted), command)


def predefined_macros(command: str) -> dict[str, str]:
    """The object-like macros ``command`` (a compiler and its flags) predefines: ``-dM -E`` of nothing."""
    argv = [*shlex.split(command), "-dM", "-E", "-"]
    if shutil.which(argv[0]) is None:
        raise HilError(f"{argv[0]} not found: install the Debian package gcc-arm-none-eabi (make deps)")
    with owned_temporary_folder("embedrl-macros-") as tmp:
        result = subprocess.run(argv, stdin=subprocess.DEVNULL, capture_output=True, text=True, cwd=tmp)
    if result.returncode != 0:
        raise HilError(f"{command} -dM -E failed ({result.returncode}): {result.stderr.strip()[-300:]}")
    macros = {}
    for line in result.stdout.splitlines():
        parts = line.split(None, 2)
        if len(parts) >= 2 and parts[0] == "#define" and "(" not in parts[1]:
            macros[parts[1]] = parts[2] if len(parts) == 3 else ""
    return macros


def _rule(check_id: str) -> str:
    return check_id.removeprefix("misra-c2012-")


def _label(path: Path, roots: dict[str, Path]) -> str:
    for prefix, root in roots.items():
        if path.is_relative_to(root):
            return prefix + str(path.relative_to(root))
    return str(path)


@functools.cache
def cppcheck_version() -> str:
    try:
        return subprocess.run(["cppcheck", "--version"], capture_output=True, text=True).stdout.strip()
    except OSError:
        return "cppcheck not installed"
