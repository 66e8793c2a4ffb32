"""HIL test helpers: running `embedrl hil run` on a given guest, booting a provider or skipping.

``EMBEDRL_REQUIRE_SANDBOXES`` (e.g. ``uml,qemu``, set by CI) turns a provider that is not installed
from a skip into a failure.
"""

from __future__ import annotations

import json
import os
from pathlib import Path
from typing import Any

import pytest

import embedrl.hil.sandbox as sandbox
from embedrl.cli import build_parser
from embedrl.hil.options import RunOptions
from embedrl.hil.run import run
from embedrl.hil.sandbox import Guest, Provider, SandboxError

REQUIRED = {p for p in os.environ.get("EMBEDRL_REQUIRE_SANDBOXES", "").split(",") if p}


def boot_or_skip(provider: Provider, workdir: Path) -> Guest:
    """Boot ``provider`` (self-tested); skip, saying why, only where it really cannot work here."""
    reason = provider.missing()
    if reason:
        if provider.name in REQUIRED:
            pytest.fail(f"{provider.label} is required here but unavailable: {reason}")
        pytest.skip(f"{provider.label} unavailable on this machine: {reason}")
    try:
        return sandbox.open_guest(provider, workdir)
    except SandboxError as exc:
        if exc.diagnosis is not None and exc.diagnosis.cause in ("cpu-fpu", "kvm"):
            pytest.skip(f"{provider.label} cannot run on this CPU: {exc}")  # another provider covers it
        raise


def run_options(export_dir: Path, *argv: str) -> RunOptions:
    """The options ``embedrl hil run --export-dir export_dir *argv`` stands for."""
    from embedrl.hil import coverage

    args = build_parser().parse_args(["hil", "run", "--export-dir", str(export_dir), *argv])
    folder = coverage.folder_of(args.json) if args.coverage else None  # as the command turns the flag
    return RunOptions.of({**vars(args), "coverage": folder})


def hil_report(guest: Guest | None, export_dir: Path, *argv: str) -> dict[str, Any]:
    """The report of ``embedrl hil run`` on ``guest`` (None: the run boots its own sandbox), as its
    ``--json`` file holds it."""
    report: dict[str, Any] = json.loads(json.dumps(run(run_options(export_dir, *argv), guest)))
    return report


def hil(guest: Guest | None, export_dir: Path, tmp_path: Path, *extra: str) -> dict[str, Any]:
    """:func:`hil_report` of a run that must pass."""
    report = hil_report(guest, export_dir, *extra)
    assert report["verdict"]["passed"], report["verdict"]["failures"]
    return report
