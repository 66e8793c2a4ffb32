"""Every CAN sandbox provider on this machine runs a real lock-step HIL episode over vcan.

One test per provider candidate (host, each UML kernel, QEMU), each on a guest of that provider: its own
for host and UML (a boot takes seconds), the session's QEMU guest for QEMU (``qemu_guest``, booted and
self-tested by the same :func:`embedrl.hil.sandbox.open_guest`, shared with the other QEMU tests: a boot
under pure emulation takes about a minute). A provider is skipped only where it really cannot work (not
installed, or a known CPU incompatibility), and the skip says why; CI sets
``EMBEDRL_REQUIRE_SANDBOXES=uml,qemu`` so those two cannot silently skip.
"""

from __future__ import annotations

import os
import signal
import subprocess
import sys
from collections.abc import Iterator
from pathlib import Path
from typing import Any

import pytest

import embedrl.hil.sandbox as sandbox
from embedrl.hil.sandbox import Guest, Provider
from embedrl.hil.sandbox.qemu import QemuProvider
from tests.conftest import marks_its_users
from tests.hil.helpers import boot_or_skip, hil
from tests.test_reaper import ended_within_deadline

pytestmark = pytest.mark.slow
CANDIDATES = sandbox.providers("auto")
SHARED_GUESTS = {QemuProvider.name: "qemu_guest"}
"""Providers whose guest the session shares (a fixture of tests/hil/conftest.py) instead of a boot here."""


def _candidate(provider: Provider) -> Any:
    """A provider as a parameter of :func:`provider_guest`, in the ``qemu`` tier if it is QEMU."""
    qemu = [pytest.mark.qemu] if provider.name == QemuProvider.name else []
    return pytest.param(provider, id=provider.slug, marks=qemu)


@pytest.fixture(scope="module", params=[_candidate(p) for p in CANDIDATES])
@marks_its_users("sandbox")
def provider_guest(
    request: pytest.FixtureRequest, tmp_path_factory: pytest.TempPathFactory
) -> Iterator[Guest]:
    provider: Provider = request.param
    if provider.name in SHARED_GUESTS:
        yield request.getfixturevalue(SHARED_GUESTS[provider.name])  # closed when the session ends
        return
    guest = boot_or_skip(provider, tmp_path_factory.mktemp(provider.slug))
    yield guest
    guest.close()


def test_a_lock_step_episode_over_vcan_equals_the_simulation(
    provider_guest: Guest, export_dir: Path, tmp_path: Path
) -> None:
    log = tmp_path / "frames.log"
    # A generous watchdog: Python under pure emulation on a loaded machine can take longer than 500 ms a
    # step, and this test is about the provider, not the node's timing.
    report = hil(
        provider_guest, export_dir, tmp_path, "--episodes", "1", "--seed", "7", "--log", str(log),
        "--timeout-ms", "5000",
    )  # fmt: skip
    assert report["sandbox"] == provider_guest.provider
    assert report["sandbox_detail"] == provider_guest.description
    assert report["episodes"] == 1 and report["faults"] == 0
    assert report["successes"] == report["simulation"]["successes"] == 1
    assert report["outcomes_differing_from_simulation"] == []
    assert report["max_action_abs_diff"] <= 1e-5 and report["first_divergent_step"] is None
    assert report["frames_tx"] == 3 * (report["steps"] + report["retries"]) and report["rx_timeouts"] == 0
    assert report["crc_errors"] == 0 and report["sequence_errors"] == 0
    lines = log.read_text().splitlines()  # written inside the guest, moved to where it was asked for
    assert len(lines) == report["frames_tx"] + report["frames_rx"]


OWNER = """
import sys, tempfile, time
from pathlib import Path
import embedrl.hil.sandbox as sandbox
guest = sandbox.select("uml", Path(sys.argv[1]), say=lambda _: None)
print(guest.process.pid, flush=True)
time.sleep(600)
"""
"""A process that boots a User-Mode Linux guest and waits to be killed."""


@pytest.mark.sandbox
def test_a_guest_ends_with_the_process_that_booted_it_even_on_sigkill(tmp_path: Path) -> None:
    if all(p.missing() for p in sandbox.providers("uml")):
        pytest.skip("no User-Mode Linux here")
    script = tmp_path / "owner.py"
    script.write_text(OWNER)
    owner = subprocess.Popen([sys.executable, str(script), str(tmp_path)], stdout=subprocess.PIPE, text=True)
    assert owner.stdout is not None
    pgid = int(owner.stdout.readline())  # the guest's process group: UML and the host processes it forked
    os.killpg(pgid, 0)
    owner.send_signal(signal.SIGKILL)
    owner.wait()
    assert ended_within_deadline(pgid), "the guest outlived the killed process that booted it"
