"""What a sign-off needs beside the figures: the conditions they were measured under (compilers and flags
per target, embedrl's version and git commit, dates, the command that made each artefact) and the
deployed program's entry points in their call order, read from the headers the program is built from."""

from __future__ import annotations

import re
import sys
from datetime import UTC, datetime
from pathlib import Path
from typing import Any

from embedrl.common import source_commit
from embedrl.export.build import RUNTIME_C

NODE_HEADER = RUNTIME_C / "node" / "node.h"
CALLS = {
    "node_receive_ids": (1, "start-up, once", "the CAN IDs to open the transport with (transport_open)"),
    "node_init": (2, "start-up, once, after transport_open",
                  "the node's state and counters; calls policy_reset (the policy at zero state)"),
    "node_poll": (3, "every pass of the main loop, before waiting for a frame",
                  "watchdog (no valid observation for timeout_ms: SAFE, safe action sent) and the periodic "
                  "status; returns the ms to wait at most"),
    "node_on_frame": (4, "each frame transport_recv returns",
                      "checks ID, length, CRC, counter and ranges; when an observation's frames are "
                      "complete, calls policy_step once and sends the action"),
    "node_on_bus_state": (5, "an error frame reports the controller's state",
                          "the bus state sent in NodeDiag"),
    "node_link_lost": (6, "the interface failed (SocketCAN main only)", "SAFE until the link is back"),
    "node_link_restored": (7, "the interface was re-opened", "announces SAFE; recovery as after a timeout"),
    "_reset": (8, "start-up, each episode start (EpisodeStart, a policy with memory) and on entering SAFE: "
               "node_init and node_on_frame call it",
               "recurrent state to zero (nothing to do without memory)"),
    "_step": (9, "once per sample period, when an observation is complete (node_on_frame)",
              "one inference; a non-finite observation or result writes the safe action and returns an "
              "error"),
}  # fmt: skip
"""Each public function of node.h and the generated policy header (``_step``: ``<name>_step``): its place in
the call order, when it is called and what it does. A test keeps it complete."""
_PROTOTYPE = re.compile(r"^((?:const |unsigned )?\w+\s*\*?\s*)(\w+)\((.*)\);\s*$", re.M)


def measurement_conditions(
    export: dict[str, Any],
    hils: list[tuple[str, dict[str, Any]]],
    coding_tool: str,
    coverage: dict[str, Any] | str | None = None,
) -> dict[str, Any]:
    """The compilers per target (and the coverage builds of ``coverage``, the report's measured coverage: the
    verification vectors' and C tests', each merged HIL run's node), the tools, and per artefact its
    command, date and embedrl commit."""
    unknown = {"command": None, "version": None}
    compilers = [{"target": "host", **export["compiler"]}]
    for name, t in export.get("targets", {}).items():
        compilers.append({"target": name, **(t.get("compiler") or unknown)})
    if isinstance(coverage, dict):
        compilers.append({"target": "host, coverage: verification vectors and C tests", "key": "coverage",
                          **coverage["compiler"]})  # fmt: skip
        hil_runs = [s for s in coverage["sources"] if s["source"].startswith("HIL run")]
        for n, source in enumerate(hil_runs):
            compilers.append({
                "target": f"host, coverage: the node of {source['source']}", "key": f"coverage-hil-{n}",
                "again": "run it again with --coverage", **(source.get("compiler") or unknown),
            })  # fmt: skip
    made = [_made("export folder (export_report.json)", export.get("provenance") or {}, export["tool"])]
    for name, h in hils:
        made.append(_made(f"HIL report {name}", h.get("provenance") or {}, None))
    made.append({
        "artefact": "this page", "command": " ".join(sys.argv), "commit": _commit(source_commit()),
        "date": datetime.now(UTC).isoformat(timespec="seconds"), "tool": None,
    })  # fmt: skip
    return {"compilers": compilers, "made": made, "tool": export["tool"], "coding_tool": coding_tool}


def _made(artefact: str, provenance: dict[str, Any], tool: str | None) -> dict[str, Any]:
    command = provenance.get("command")
    return {
        "artefact": artefact,
        "command": " ".join(command) if isinstance(command, list) else None,
        "date": provenance.get("date"),
        "commit": _commit(provenance.get("commit")),
        "tool": tool,
    }


def _commit(commit: Any) -> str | None:
    """``sha`` (with ``+ modified files`` when the checkout differed from it); None when not recorded."""
    sha = commit.get("sha") if isinstance(commit, dict) else None
    if not isinstance(sha, str):
        return None
    return sha + (" + modified files" if commit.get("modified") else "")


def entry_points(export_dir: Path, name: str) -> list[dict[str, Any]]:
    """The public functions of the generated ``c/<name>.h`` and of ``runtime_c/node/node.h`` in their call
    order: prototype, header, when called, what it does (from :data:`CALLS`; a function missing there is
    listed last, ``when`` None)."""
    rows = []
    headers = ((export_dir / "c" / f"{name}.h", f"c/{name}.h"), (NODE_HEADER, "runtime_c/node/node.h"))
    for header, label in headers:
        for returns, function, args in _PROTOTYPE.findall(header.read_text()):
            key = function if function.startswith("node_") else function.removeprefix(name)
            order, when, what = CALLS.get(key, (len(CALLS) + 1, None, None))
            rows.append({
                "order": order, "function": function, "prototype": f"{returns.strip()} {function}({args})",
                "header": label, "when": when, "what": what,
            })  # fmt: skip
    return sorted(rows, key=lambda r: (r["order"], r["function"]))
