"""Reading a dead guest's console: which known cause killed it, and the lines that show it.

A guest (User-Mode Linux or QEMU) that ends without a result leaves only its console log. The rules
below name the causes seen on this project's machines, most specific first: an FPU/XSAVE mismatch
between a UML kernel and the host CPU also ends in a kernel panic, so it must be recognised before the
generic panic.
"""

from __future__ import annotations

import re
from dataclasses import dataclass

EVIDENCE_LINES = 4
"""How many of the log's last relevant lines a diagnosis quotes."""


@dataclass(frozen=True)
class Rule:
    cause: str
    pattern: re.Pattern[str]
    explanation: str


@dataclass(frozen=True)
class Diagnosis:
    """Why a guest died: a short cause code, a sentence for the user, and the log lines that show it."""

    cause: str
    explanation: str
    evidence: tuple[str, ...]

    def __str__(self) -> str:
        quoted = " | ".join(self.evidence)
        return f"{self.explanation}" + (f" (console: {quoted})" if quoted else "")


RULES = (
    Rule(
        "cpu-fpu",
        re.compile(r"ptrace set fp regs failed|ptrace_setfpregs|FP registers.*failed", re.I),
        "this UML kernel cannot run on this CPU: the host rejects its FPU state (CPUs with AMX need "
        "UML >= 7.2; `make deps` provides one)",
    ),
    Rule(
        "glibc",
        re.compile(r"version `GLIBC_[0-9.]+' not found"),
        "the UML binary needs a newer glibc than this system's (it must be patched to its own libc: "
        "`make deps`)",
    ),
    Rule(
        "kvm",
        re.compile(
            r"kvm_buf_set_msrs|failed to set MSR|Could not access KVM|KVM: entry failed|kvm.*failed", re.I
        ),
        "QEMU could not run the guest with KVM on this machine (nested virtualisation does not work here)",
    ),
    Rule(
        "out-of-memory",
        re.compile(
            r"Out of memory|oom-kill|invoked oom-killer|Cannot allocate memory|no enough memory", re.I
        ),
        "the guest ran out of memory",
    ),
    Rule(
        "missing-modules",
        re.compile(
            r"embedrl: (insmod|modprobe) .* failed|Module \S+ not found|could not insert|"
            r"Unknown device type|embedrl: no vcan0",
            re.I,
        ),
        "the guest kernel lacks the CAN modules (can, can-raw, can-dev, vcan), so vcan0 cannot exist",
    ),
    Rule(
        "kernel-panic",
        re.compile(r"Kernel panic|Attempted to kill init|BUG: |Oops", re.I),
        "the guest kernel panicked",
    ),
)


def diagnose(log: str, timed_out: bool = False, timeout_s: float | None = None) -> Diagnosis:
    """Name the cause of a guest's death from its console ``log``.

    ``timed_out``: the guest was stopped because it gave no result in time; that is the cause unless
    the log shows a more specific one.
    """
    lines = [_clean(line) for line in log.splitlines()]
    lines = [line for line in lines if line]
    for rule in RULES:
        hits = [line for line in lines if rule.pattern.search(line)]
        if hits:
            return Diagnosis(rule.cause, rule.explanation, tuple(hits[-EVIDENCE_LINES:]))
    tail = tuple(lines[-EVIDENCE_LINES:])
    if timed_out:
        limit = f" within {timeout_s:.0f} s" if timeout_s is not None else ""
        return Diagnosis("timeout", f"the guest gave no result{limit} and was stopped", tail)
    if not lines:
        return Diagnosis("no-output", "the guest exited at once and printed nothing", ())
    return Diagnosis("unknown", "the guest ended without a result and its console names no known cause", tail)


_ANSI = re.compile(r"\x1b\[[0-9;?]*[A-Za-z]|\r")


def _clean(line: str) -> str:
    return _ANSI.sub("", line).strip()
