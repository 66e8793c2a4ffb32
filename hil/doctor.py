"""``embedrl hil doctor``: every CAN sandbox provider on this machine, booted and self-tested.

Prints the machine's CPU (whether it has AMX decides which UML kernels run), a line every
:data:`PROGRESS_S` while a provider boots and self-tests (a QEMU guest under pure emulation takes minutes),
and one row per provider: works or not, boot time, and the reason (the self-test's result or the diagnosed
failure).
"""

from __future__ import annotations

import platform
import threading
import time
from collections.abc import Callable, Iterator
from contextlib import contextmanager
from dataclasses import asdict
from pathlib import Path
from typing import Any

from embedrl.common import owned_temporary_folder
from embedrl.hil import sandbox

CPUINFO = Path("/proc/cpuinfo")
PROGRESS_S = 5.0
"""While a provider boots and runs its self-test, a line every this many seconds says it still does."""


def machine() -> dict[str, Any]:
    """CPU model and the flags that matter to the sandboxes, the host kernel."""
    model, flags, cores = "unknown", set[str](), 0
    try:
        lines = CPUINFO.read_text().splitlines()
    except OSError:
        lines = []
    for line in lines:
        key, _, value = (part.strip() for part in line.partition(":"))
        if key == "processor":
            cores += 1
        elif key == "model name" and model == "unknown":
            model = value
        elif key == "flags" and not flags:
            flags = set(value.split())
    return {
        "cpu": model,
        "amx": any(f.startswith("amx") for f in flags),
        "cores": cores or None,
        "host_kernel": platform.release(),
        "kvm_device": Path("/dev/kvm").exists(),
    }


@contextmanager
def _progress(say: Callable[[str], None], label: str, every_s: float) -> Iterator[None]:
    """While the block runs, ``say`` every ``every_s`` that ``label`` is still booting or self-testing."""
    done = threading.Event()
    start = time.monotonic()

    def tick() -> None:
        while not done.wait(every_s):
            say(f"  {label}: still booting or self-testing, {time.monotonic() - start:.0f} s")

    thread = threading.Thread(target=tick, daemon=True)
    thread.start()
    try:
        yield
    finally:
        done.set()
        thread.join()


def doctor(
    say: Callable[[str], None] = print,
    mode: str = "auto",
    progress_s: float = PROGRESS_S,
    every: bool = False,
) -> dict[str, Any]:
    """Check the providers of ``mode`` in the order ``--sandbox mode`` tries them: for ``auto`` up to the
    first that works (what it picks) unless ``every``, for a named provider every candidate; the report with
    ``first_working`` and the providers left unchecked (``not_checked``: a QEMU guest's emulated boot takes
    minutes). A line every ``progress_s`` while one boots."""
    info = machine()
    say(f"machine: {info['cpu']}, AMX {'yes' if info['amx'] else 'no'}, host kernel {info['host_kernel']}")
    checks: list[dict[str, Any]] = []
    not_checked: list[str] = []
    with owned_temporary_folder("embedrl-doctor-") as tmp:
        for provider in sandbox.providers(mode):
            if not every and mode == sandbox.AUTO and any(c["works"] for c in checks):
                not_checked.append(provider.label)
                continue
            say(f"checking {provider.label} ...")
            start = time.monotonic()
            with _progress(say, provider.label, progress_s):
                result = sandbox.check(provider, Path(tmp))
            checks.append({**asdict(result), "check_s": round(time.monotonic() - start, 2)})
    first = next((c["label"] for c in checks if c["works"]), None)
    return {
        "machine": info,
        "mode": mode,
        "providers": checks,
        "first_working": first,
        "not_checked": not_checked,
    }


def print_table(report: dict[str, Any], say: Callable[[str], None] = print) -> None:
    rows = [("provider", "works", "boot [s]", "reason")]
    for c in report["providers"]:
        boot = "-" if c["boot_s"] is None else f"{c['boot_s']:.1f}"
        rows.append((c["label"], "yes" if c["works"] else "no", boot, c["reason"]))
    widths = [max(len(r[i]) for r in rows) for i in range(3)]
    for r in rows:
        say(f"{r[0]:<{widths[0]}}  {r[1]:<{widths[1]}}  {r[2]:>{widths[2]}}  {r[3]}")
    for label in report.get("not_checked", []):
        say(f"{label}: not checked (one before it works; `embedrl hil doctor --all` boots every provider)")
    first = report["first_working"]
    say(f"--sandbox {report['mode']} uses: {first}" if first else "no provider works: see the reasons above")
