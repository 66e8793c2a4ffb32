"""HIL test helpers: running `embedrl hil run` on a given guest, booting a provider or skipping.

``EMBEDRL_REQUIRE_SANDBOXES`` (e.g. ``uml,qemu``, set by CI) turns a provider that is not installed
from a skip into a failure.
"""

from __future__ import annotations

import json
import os
import shutil
import tempfile
from concurrent.futures import Future, ThreadPoolExecutor
from pathlib import Path
from typing import Any

import pytest

import embedrl.hil.sandbox as sandbox
from embedrl.cli import build_parser
from embedrl.hil.cli import cmd_run
from embedrl.hil.sandbox import Guest, Provider, SandboxError

REQUIRED = {p for p in os.environ.get("EMBEDRL_REQUIRE_SANDBOXES", "").split(",") if p}
EARLY_PROVIDERS = ("qemu",)
"""Providers whose boot starts as soon as a test that needs them is selected: QEMU under pure emulation
boots in ~25 s on one core, which then overlaps the tests that run before it."""

_early: dict[str, Future[Guest]] = {}
_workdirs: list[Path] = []
_pool = ThreadPoolExecutor(max_workers=len(EARLY_PROVIDERS), thread_name_prefix="early-boot")


def boot_early(provider: Provider) -> None:
    """Start booting ``provider`` in the background; :func:`boot_or_skip` then takes that guest."""
    if provider.slug in _early or provider.missing():
        return
    workdir = Path(tempfile.mkdtemp(prefix=f"embedrl-test-{provider.slug}-"))
    _workdirs.append(workdir)
    _early[provider.slug] = _pool.submit(sandbox.open_guest, provider, workdir)


def close_early() -> None:
    """At the session's end: close the early guests no test took, remove the early boots' folders."""
    for future in _early.values():
        future.cancel()  # not started yet: never boots
    _pool.shutdown(wait=True)
    for future in _early.values():
        if not future.cancelled() and future.exception() is None:
            future.result().close()
    _early.clear()
    for workdir in _workdirs:
        shutil.rmtree(workdir, ignore_errors=True)


def boot_or_skip(provider: Provider, workdir: Path) -> Guest:
    """Boot ``provider`` (self-tested); skip, saying why, only where it really cannot work here."""
    reason = provider.missing()
    if reason:
        if provider.name in REQUIRED:
            pytest.fail(f"{provider.label} is required here but unavailable: {reason}")
        pytest.skip(f"{provider.label} unavailable on this machine: {reason}")
    try:
        early = _early.pop(provider.slug, None)
        return early.result() if early else sandbox.open_guest(provider, workdir)
    except SandboxError as exc:
        if exc.diagnosis is not None and exc.diagnosis.cause in ("cpu-fpu", "kvm"):
            pytest.skip(f"{provider.label} cannot run on this CPU: {exc}")  # another provider covers it
        raise


def hil(guest: Guest | None, export_dir: Path, tmp_path: Path, *extra: str) -> dict[str, Any]:
    """``embedrl hil run`` on ``guest`` (None: the command boots its own sandbox); the JSON report."""
    out = tmp_path / "hil.json"
    args = build_parser().parse_args(
        ["hil", "run", "--export-dir", str(export_dir), "--json", str(out), *extra]
    )
    assert cmd_run(args, guest) == 0
    report: dict[str, Any] = json.loads(out.read_text())
    return report
