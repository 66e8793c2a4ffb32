"""Coverage of the deployed C, the report's "coverage" check: clang's source-based coverage (lines, branches,
MC/DC conditions) of the generated policy over the export's verification observations and the non-finite
probes, and of the node (``node.c``, ``e2e.c``) and its CAN glue (``policy_io.c``, ``slcan.c``) over their C
unit tests (``make -C runtime_c coverage``, clang-19 and llvm-19).

The goal per file is every line and every branch taken both ways, and MC/DC (each condition of a decision
with two or more shown to change its outcome alone) on at least :data:`GOAL_MCDC` percent of the conditions.
What stays uncovered is listed, each with its reason from ``runtime_c/coverage_reasons.toml``; a gap
without one fails the check. The policy's C is only measured once it is known to be the generator's (the
caller regenerates it first): it runs on this host.
"""

from __future__ import annotations

import json
import re
import shutil
import subprocess
import tempfile
import tomllib
from dataclasses import dataclass
from pathlib import Path
from typing import Any

import numpy as np

from embedrl.export.build import RUNTIME_C

GOAL_LINES = 100.0
GOAL_BRANCHES = 100.0
GOAL_MCDC = 95.0
REASONS = RUNTIME_C / "coverage_reasons.toml"
CLANG = "clang-19"
"""The compiler ``make coverage`` uses (its COV_CC default)."""
TEST_DOUBLES = RUNTIME_C / "tests"
"""The C tests and their doubles (the fake policy's policy.c among them): measured, never reported."""
NODE_FILES = {
    "node.c": "the node: receive, watchdog, SAFE, actions and status",
    "e2e.c": "the node: E2E protection (CRC-8, counters)",
    "policy_io.c": "CAN glue: frames <-> observation and action vectors (generated from the interface)",
    "slcan.c": "CAN glue: serial CAN framing of the firmware node",
}
"""The node's files in the goal, by name, and what each is."""
OUTSIDE_GOAL = {
    "policy_dbc.c": "cantools' codec of the whole CAN database: the node calls the pack/unpack of its own "
    "frames and of no other message",
}
"""Files measured and shown but not held to the goal, and why."""
OVERFLOW = np.float32(np.finfo(np.float32).max)
"""A finite observation so large that the network's sums overflow: its own non-finite result."""
LARGE = np.float32(1e4)
"""A finite observation far outside every interface's range, whose sums stay finite."""
BRANCH_REGION_KINDS = (4, 6)
"""llvm-cov's JSON: a branch region, an MC/DC condition's branch region."""


@dataclass(frozen=True)
class Reason:
    file: str
    kind: str
    code: str
    reason: str


def probe_rows(observations: np.ndarray) -> np.ndarray:
    """The verification observations, then the probes: per position a NaN, +inf and -inf (the finite
    checks); per position +/- :data:`LARGE` (activations far past any saturation point, still finite) and
    +/- the largest float32 (sums that overflow to an infinity); and every position at the largest float32
    with the same sign and with alternating signs (infinities of both signs meeting in one sum: NaN, the
    network's own non-finite result)."""
    obs = np.asarray(observations, dtype=np.float32)
    dim = obs.shape[1]
    rows = [obs]
    for value in (np.nan, np.inf, -np.inf, LARGE, -LARGE, OVERFLOW, -OVERFLOW):
        probe = np.zeros((dim, dim), dtype=np.float32)
        np.fill_diagonal(probe, value)
        rows.append(probe)
    alternating = np.array([(-1.0) ** i for i in range(dim)], dtype=np.float32)
    whole = np.stack([np.ones(dim), -np.ones(dim), alternating, -alternating]).astype(np.float32) * OVERFLOW
    rows.append(whole)
    return np.concatenate(rows)


def measure(c_dir: Path, name: str, observations: np.ndarray) -> dict[str, Any]:
    """Build and run everything under coverage; the summary (:func:`summarise`) and the driver's codes."""
    from embedrl.export import build

    rows = probe_rows(observations)
    with tempfile.TemporaryDirectory(prefix="embedrl-coverage-") as tmp:
        work = Path(tmp)
        # a copy of the C in a folder without spaces: make then builds it where it is, and llvm-cov names
        # the sources read below by their real paths (not a temporary link's)
        shutil.copytree(c_dir, work / "c")
        (work / "obs.f32").write_bytes(np.ascontiguousarray(rows, dtype="<f4").tobytes())
        build.make(
            "coverage", work / "c", work, extra={"COVERAGE_OBS": str(work / "obs.f32"), "POLICY_NAME": name}
        )
        cov = work / "coverage"
        summary = summarise(json.loads((cov / "coverage.json").read_text()),
                            (cov / "coverage.lcov").read_text(), f"{name}.c", load_reasons())  # fmt: skip
        codes = [int(line.split()[2]) for line in (cov / "policy_steps.txt").read_text().splitlines()
                 if line.startswith("A ")]  # fmt: skip
    summary["compiler"] = _version(CLANG)
    summary["probes"] = {"rows": len(rows), "verification_rows": len(observations),
                         "codes": {str(c): codes.count(c) for c in sorted(set(codes))}}  # fmt: skip
    return summary


def _version(tool: str) -> str:
    """The first line of ``tool --version`` (the measurement conditions)."""
    result = subprocess.run([tool, "--version"], capture_output=True, text=True)
    return (result.stdout.strip().splitlines() or [tool])[0]


def load_reasons(path: Path = REASONS) -> list[Reason]:
    entries = tomllib.loads(path.read_text()).get("gap", [])
    return [Reason(e["file"], e["kind"], e["code"], " ".join(e["reason"].split())) for e in entries]


def summarise(
    export: dict[str, Any],
    lcov: str,
    policy_file: str,
    reasons: list[Reason],
    policy_source: Path | None = None,
) -> dict[str, Any]:
    """Per file of the goal (the policy, then the node's) and outside it: lines, branches and MC/DC
    conditions covered of all, and each gap (line not run, branch direction never taken, condition not
    shown independent) with its reason or None. The policy's source is read from ``policy_source`` if
    given (make may have built it through a temporary link: a folder with spaces)."""
    roles = {policy_file: "the generated policy", **NODE_FILES}
    lines_not_run = _lines_not_run(lcov)
    files = []
    for f in sorted(export["data"][0]["files"], key=lambda f: f["filename"]):
        base = Path(f["filename"]).name
        if (base not in roles and base not in OUTSIDE_GOAL) or Path(f["filename"]).is_relative_to(
            TEST_DOUBLES
        ):
            continue
        text = Path(f["filename"]).read_text().splitlines()
        gaps = _gaps(f, text, lines_not_run.get(f["filename"], []))
        in_goal = base in roles
        for gap in gaps:
            gap["reason"] = next((r.reason for r in reasons if r.file == base and explains(r, gap)), None)
        s = f["summary"]
        row = {
            "file": base,
            "role": roles.get(base) or OUTSIDE_GOAL[base],
            "in_goal": in_goal,
            **{
                k: {"covered": s[k]["covered"], "count": s[k]["count"]} for k in ("lines", "branches", "mcdc")
            },
            "gaps": gaps if in_goal else [],
        }
        row["meets_goal"] = in_goal and _meets_goal(row)
        files.append(row)
    order = [policy_file, *NODE_FILES, *OUTSIDE_GOAL]
    files.sort(key=lambda r: order.index(str(r["file"])))
    return {"files": files, "goal": {"lines": GOAL_LINES, "branches": GOAL_BRANCHES, "mcdc": GOAL_MCDC},
            "llvm_cov_json": export.get("version")}  # fmt: skip


def explains(reason: Reason, gap: dict[str, Any]) -> bool:
    """A reason explains a gap of its kind whose source text is its ``code`` (a line) or contains it (a
    branch or condition: the decision around it may vary)."""
    if reason.kind != gap["kind"]:
        return False
    return bool(reason.code == gap["code"] if gap["kind"] == "line" else reason.code in gap["code"])


def percent(part: dict[str, int]) -> float | None:
    """Covered of all, in percent; None where there is nothing to cover."""
    return 100.0 * part["covered"] / part["count"] if part["count"] else None


def _meets_goal(row: dict[str, Any]) -> bool:
    def at_least(part: dict[str, int], goal: float) -> bool:
        p = percent(part)
        return p is None or p >= goal

    return (
        at_least(row["lines"], GOAL_LINES)
        and at_least(row["branches"], GOAL_BRANCHES)
        and at_least(row["mcdc"], GOAL_MCDC)
    )


def _lines_not_run(lcov: str) -> dict[str, list[int]]:
    """Per source file, the lines LCOV records with a count of 0."""
    out: dict[str, list[int]] = {}
    current = None
    for line in lcov.splitlines():
        if line.startswith("SF:"):
            current = out.setdefault(line[3:], [])
        elif line.startswith("DA:") and current is not None:
            number, count = line[3:].split(",")[:2]
            if int(count) == 0:
                current.append(int(number))
    return out


def _span(text: list[str], l1: int, c1: int, l2: int, c2: int) -> str:
    """The source from (l1, c1) to (l2, c2), 1-based and end-exclusive, on one line."""
    if l1 == l2:
        return text[l1 - 1][c1 - 1 : c2 - 1].strip()
    parts = [text[l1 - 1][c1 - 1 :], *text[l1 : l2 - 1], text[l2 - 1][: c2 - 1]]
    return re.sub(r"\s+", " ", " ".join(parts)).strip()


def _gaps(f: dict[str, Any], text: list[str], not_run: list[int]) -> list[dict[str, Any]]:
    """Lines not run, branch directions never taken, MC/DC conditions not shown independent."""
    gaps = [{"kind": "line", "line": n, "code": text[n - 1].strip(), "detail": "never run"} for n in not_run]
    branches = sorted(
        (b for b in f["branches"] if b[6] == 0 and b[8] in BRANCH_REGION_KINDS), key=lambda b: (b[0], b[1])
    )
    for b in branches:
        for taken, count in (("true", b[4]), ("false", b[5])):
            if count == 0:
                code = _span(text, *b[:4])
                gaps.append({"kind": "branch", "line": b[0], "code": code, "detail": f"never {taken}"})
    for record in f["mcdc_records"]:
        l1, c1, l2, c2, covered = record[0], record[1], record[2], record[3], record[-1]
        inside = [b for b in branches if (l1, c1) <= (b[0], b[1]) and (b[2], b[3]) <= (l2, c2)]
        decision = _span(text, l1, c1, l2, c2)
        for i, shown in enumerate(covered):
            if not shown:
                code = _span(text, *inside[i][:4]) if i < len(inside) else f"condition {i + 1}"
                detail = f"not shown to decide `{decision}` alone (condition {i + 1} of {len(covered)})"
                gaps.append({"kind": "condition", "line": l1, "code": code, "detail": detail})
    gaps.sort(key=lambda g: (g["line"], g["kind"]))
    return gaps


def check(summary: dict[str, Any] | str) -> tuple[bool, str]:
    """The verdict's line: passed when each gap in a file of the goal has its reason (a file that meets the
    goal may still list MC/DC conditions below 100 percent)."""
    if isinstance(summary, str):
        return False, f"not measured: {summary}"
    unexplained = [(f["file"], g) for f in summary["files"] for g in f["gaps"] if g["reason"] is None]
    figures = "; ".join(
        f"{f['file']} " + ", ".join(f"{label} {shown(f[k])}" for k, label in LABELS.items())
        for f in summary["files"]
        if f["in_goal"]
    )
    if unexplained:
        file, gap = unexplained[0]
        first = f"{file}:{gap['line']} `{gap['code']}` ({gap['kind']}, {gap['detail']})"
        return False, f"{len(unexplained)} gap(s) without a reason, first {first}; {figures}"
    gaps = sum(len(f["gaps"]) for f in summary["files"])
    return True, f"{figures}; {gaps} gap(s), each with its reason"


LABELS = {"lines": "lines", "branches": "branches", "mcdc": "MC/DC"}


def shown(part: dict[str, int]) -> str:
    """``covered/count (p%)``, or ``none`` where there is nothing to cover."""
    p = percent(part)
    return "none" if p is None else f"{part['covered']}/{part['count']} ({p:.4g}%)"
