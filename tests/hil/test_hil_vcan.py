"""The HIL contract against the compiled C node over real SocketCAN vcan0, in the sandbox ``--sandbox
auto`` picks on this machine (the verdict), plus what only the sandboxed path has.

One sandbox guest serves the whole session (the ``guest`` fixture), one QEMU guest the emulated timing
(``qemu_guest``, shared with the other QEMU tests); the first test boots its own, as the command does.
"""

from __future__ import annotations

import contextlib
import json
import os
import shutil
import signal
import tempfile
import time
from collections.abc import Callable, Iterator
from pathlib import Path
from typing import Any

import pytest

import embedrl.hil.sandbox as sandbox
from embedrl.hil.errors import HilError
from embedrl.hil.options import DEFAULT_TIMEOUT_MS
from embedrl.hil.run import ACTION_TIMEOUT_S
from embedrl.hil.sandbox import Guest
from embedrl.hil.sandbox.base import JobResult
from embedrl.hil.sandbox.qemu import TCG_SLOWDOWN
from tests.hil.contract import NODE_TIMEOUT_MS, HilContract
from tests.hil.helpers import hil, hil_report
from tests.test_user_errors import run_and_interrupt

pytestmark = pytest.mark.slow


class TestCNodeOnVcan(HilContract):
    node = "c"
    sandboxes = ("host", "uml", "qemu")
    channel = "vcan0"

    @pytest.fixture
    def where(self, guest: Guest) -> Guest | None:
        return guest

    lying_flags = ("--trust-c",)

    def lying_export(self, export_dir: Path, tmp_path: Path) -> Path:
        """The generated policy_step wrapped: NaN in every action, POLICY_OK returned."""
        lying = tmp_path / "lying"
        shutil.copytree(export_dir, lying)
        source = lying / "c" / "policy.c"
        text = source.read_text().replace("int32_t policy_step(", "static int32_t honest_policy_step(")
        source.write_text(
            text + "\nint32_t policy_step(const float obs[POLICY_OBS_DIM], float act[POLICY_ACT_DIM])\n{\n"
            "    (void)honest_policy_step(obs, act);\n"
            "    for (uint32_t i = 0u; i < POLICY_ACT_DIM; ++i) {\n        act[i] = NAN;\n    }\n"
            "    return POLICY_OK;\n}\n"
        )
        return lying


def test_the_command_boots_its_own_sandbox(export_dir: Path, tmp_path: Path) -> None:
    report = hil(None, export_dir, tmp_path, "--episodes", "1", "--timeout-ms", str(NODE_TIMEOUT_MS))
    assert report["sandbox"] in TestCNodeOnVcan.sandboxes and report["successes"] == 1


class _FailingGuest(Guest):
    """A guest whose session dies with a Python error, as a broken environment inside a guest would."""

    provider, description, boot_s = "uml", "uml: failing", 0.1

    def run(self, argv: list[str], cwd: Path, timeout_s: float) -> JobResult:
        return JobResult(
            1, "Traceback (most recent call last):\nModuleNotFoundError: No module named 'can'\n"
        )


def test_a_session_failing_inside_the_guest_names_the_cause_and_keeps_the_files(
    export_dir: Path, tmp_path: Path
) -> None:
    with pytest.raises(HilError) as caught:
        hil(_FailingGuest(), export_dir, tmp_path, "--episodes", "1")
    message = str(caught.value)
    assert message.startswith("uml: failing: the HIL session failed (status 1): ")
    assert "No module named 'can'" in message
    kept = Path(message.rsplit(" kept in ", 1)[1].rstrip("]"))
    assert (kept / "build" / "policy_node").is_file()
    shutil.rmtree(kept)


def test_a_successful_run_leaves_no_temporary_folder(guest: Guest, export_dir: Path, tmp_path: Path) -> None:
    before = set(Path(tempfile.gettempdir()).glob("embedrl-hil-*"))
    hil(guest, export_dir, tmp_path, "--episodes", "1")
    assert set(Path(tempfile.gettempdir()).glob("embedrl-hil-*")) == before


def _processes_mentioning(text: str) -> list[str]:
    """Command lines of the running processes whose command line or working folder mentions ``text``."""
    found = []
    for proc in Path("/proc").iterdir():
        if not proc.name.isdigit():
            continue
        try:
            cmdline = (proc / "cmdline").read_bytes().replace(b"\0", b" ").decode(errors="replace")
            cwd = os.readlink(proc / "cwd")
        except OSError:
            continue  # gone, or a kernel thread
        if text in cmdline or text in cwd:
            found.append(f"{proc.name}: {cmdline}")
    return found


@pytest.mark.parametrize("sig", [signal.SIGINT, signal.SIGTERM])
def test_two_signals_2_s_apart_end_the_guest_and_everything_it_started(
    sig: signal.Signals, export_dir: Path, tmp_path: Path
) -> None:
    (tmp_path / "tmp").mkdir()  # TMPDIR of the command: the guest's work folder is in it
    argv = [
        "hil",
        "run",
        "--export-dir",
        str(export_dir),
        "--json",
        str(tmp_path / "h.json"),
        "--episodes",
        "5000",
    ]
    # signalled while the guest runs the session (a busy guest does not read a stop request)
    done = run_and_interrupt(argv, tmp_path, "running 5000 episode(s)", sig, again_after_s=2.0, settle_s=3.0)
    assert done.returncode == 128 + sig, done.stderr
    assert done.stderr.strip().splitlines()[-1] == "interrupted", done.stderr
    assert done.seconds_to_exit < 5.0  # type: ignore[attr-defined]
    deadline = time.monotonic() + 5.0
    while _processes_mentioning(str(tmp_path)) and time.monotonic() < deadline:
        time.sleep(0.1)  # SIGKILLed processes may take a moment to be reaped
    assert _processes_mentioning(str(tmp_path)) == []
    assert not [p for p in (tmp_path / "tmp").iterdir() if p.name.startswith("embedrl")]
    assert not (tmp_path / "h.json").exists()


@pytest.mark.qemu
def test_under_qemu_emulation_the_default_timing_passes_five_episodes(
    qemu_guest: Guest, export_dir: Path, tmp_path: Path
) -> None:
    """Python runs ~10x slower under pure emulation: the default watchdog and answer wait stretch with it
    (by the guest's ``slowdown``), on the session's QEMU guest; the command that boots its own QEMU for
    ``--sandbox qemu`` stretches them alike (the next test)."""
    report = hil(qemu_guest, export_dir, tmp_path, "--sandbox", "qemu", "--episodes", "5", "--seed", "0")
    assert report["sandbox"] == "qemu" and report["verdict"]["passed"], report["verdict"]
    assert report["episodes"] == 5
    assert report["node_status"]["timeouts"] == 0 and report["rx_timeouts"] == 0
    assert report["node_diag"]["action_faults"] == 0


class _CapturingGuest(Guest):
    """An emulated QEMU guest that keeps the session settings of each job it is given and runs nothing."""

    provider, description, boot_s, slowdown = "qemu", "qemu: capturing", 0.1, TCG_SLOWDOWN

    def __init__(self, folder: Path) -> None:
        self.folder = folder
        self.settings: list[dict[str, Any]] = []

    def run(self, argv: list[str], cwd: Path, timeout_s: float) -> JobResult:
        self.settings.append(json.loads(Path(argv[-1]).read_text()))  # python -m embedrl.hil.session FILE
        return JobResult(1, "not run")

    def scratch(self) -> Path:
        return Path(tempfile.mkdtemp(dir=self.folder))


def test_the_command_booting_qemu_stretches_the_default_timing_as_a_given_qemu_guest_does(
    export_dir: Path, tmp_path: Path, monkeypatch: pytest.MonkeyPatch
) -> None:
    given, booted = _CapturingGuest(tmp_path), _CapturingGuest(tmp_path)

    @contextlib.contextmanager
    def opened(mode: str, workdir: Path, say: Callable[[str], None] = print) -> Iterator[Guest]:
        assert mode == "qemu"
        yield booted

    monkeypatch.setattr(sandbox, "opened", opened)  # what `--sandbox qemu` boots
    for guest in (given, None):
        with pytest.raises(HilError, match="the HIL session failed") as caught:
            hil_report(guest, export_dir, "--sandbox", "qemu", "--episodes", "5", "--seed", "0")
        shutil.rmtree(str(caught.value).rsplit(" kept in ", 1)[1].rstrip("]"))
    [by_command], [by_guest] = booted.settings, given.settings
    stretched = (round(DEFAULT_TIMEOUT_MS * TCG_SLOWDOWN), ACTION_TIMEOUT_S * TCG_SLOWDOWN)
    assert (by_command["node_timeout_ms"], by_command["action_timeout_s"]) == stretched
    assert (by_guest["node_timeout_ms"], by_guest["action_timeout_s"]) == stretched
