"""HIL over real SocketCAN, in the sandbox ``--sandbox auto`` picks on this machine.

The policy is the example TD3 actor (imitating the potential-field controller, so its episodes
succeed) exported with `embedrl export`; the node is the compiled C policy. One sandbox guest serves
the whole module (the ``guest`` fixture); the first test boots its own, as the command does.
"""

from __future__ import annotations

import json
import shutil
import tempfile
import time
from pathlib import Path
from typing import Any

import pytest

from embedrl.cli import main
from embedrl.hil.errors import HilError
from embedrl.hil.sandbox import Guest
from embedrl.hil.sandbox.base import JobResult
from tests.hil.helpers import hil

pytestmark = pytest.mark.slow
NODE_TIMEOUT_MS = 200
SAFE_MARGIN_MS = 200
"""Allowed lateness of the safe action beyond the watchdog timeout (scheduling inside UML)."""


def _hil(guest: Guest | None, export_dir: Path, tmp_path: Path, *extra: str) -> dict[str, Any]:
    return hil(guest, export_dir, tmp_path, "--timeout-ms", str(NODE_TIMEOUT_MS), *extra)


def test_lock_step_episodes_equal_the_simulation(export_dir: Path, tmp_path: Path) -> None:
    log = tmp_path / "frames.log"
    report = _hil(
        None,
        export_dir,
        tmp_path,
        "--episodes",
        "6",
        "--seed",
        "0",
        "--log",
        str(log),
        "--plot",
        str(tmp_path / "plots"),
    )
    assert report["sandbox"] in ("host", "uml", "qemu")
    assert report["episodes"] == 6 and report["faults"] == 0
    assert report["successes"] == report["simulation"]["successes"] == 6
    assert report["outcomes_differing_from_simulation"] == []
    assert report["max_action_abs_diff"] <= 1e-5 and report["first_divergent_step"] is None
    assert report["frames_tx"] == 3 * report["steps"] and report["frames_rx"] >= report["steps"]
    assert report["crc_errors"] == 0 and report["sequence_errors"] == 0 and report["rx_timeouts"] == 0
    assert 0 < report["latency_us"]["p50"] <= report["latency_us"]["p99"] <= report["latency_us"]["max"]
    for key in (
        "episodes",
        "successes",
        "collisions",
        "timeouts",
        "success_rate",
        "mean_return",
        "mean_time_s",
    ):
        assert key in report
    lines = log.read_text().splitlines()
    assert len(lines) == report["frames_tx"] + report["frames_rx"]
    sent = [line for line in lines if line.endswith(" T")]
    received = [line for line in lines if line.endswith(" R")]
    assert len(sent) == report["frames_tx"] and len(received) == report["frames_rx"]
    assert all(" vcan0 10" in line for line in sent)  # ObservationA..C (0x100..0x102)
    assert all(" vcan0 200#" in line or " vcan0 300#" in line for line in received)  # Action, NodeStatus
    assert (tmp_path / "plots" / "hil_latency.png").is_file()
    assert (tmp_path / "plots" / "hil_trajectories.png").is_file()


def test_corrupted_observation_frame_is_dropped_and_counted(
    guest: Guest, export_dir: Path, tmp_path: Path
) -> None:
    report = _hil(guest, export_dir, tmp_path, "--episodes", "1", "--inject", "corrupt")
    injection = report["injection"]
    assert injection["kind"] == "corrupt"
    assert injection["action_received"] is False  # no action computed from the corrupted observation
    assert injection["node_crc_errors_after"] == injection["node_crc_errors_before"] + 1


def test_silent_simulator_gets_the_safe_action_within_the_timeout(
    guest: Guest, export_dir: Path, tmp_path: Path
) -> None:
    report = _hil(guest, export_dir, tmp_path, "--episodes", "1", "--inject", "silent")
    injection = report["injection"]
    assert injection["safe_action_after_ms"] is not None
    assert injection["safe_action_after_ms"] <= NODE_TIMEOUT_MS + SAFE_MARGIN_MS
    assert injection["node_state"] == "SAFE"
    assert injection["expected_safe_action"] == [0.0, 0.0] and injection["safe_action"] == [0.0, 0.0]


def test_the_watchdog_sends_the_exports_own_safe_action(
    guest: Guest, export_dir: Path, tmp_path: Path
) -> None:
    # An export with --safe-action 0.1,0: the node's watchdog must send (0.1, 0), not zeros.
    safe = tmp_path / "safe-export"
    source = export_dir.parent / "td3.zip"
    assert main(["export", str(source), "--out", str(safe), "--episodes", "0", "--safe-action", "0.1,0"]) == 0
    assert json.loads((safe / "interface.json").read_text())["safe_action"] == [0.1, 0.0]
    assert "#define POLICY_SAFE_ACTION {0.100000001f, 0.0f}" in (safe / "c" / "policy.h").read_text()
    report = _hil(guest, safe, tmp_path, "--episodes", "1", "--inject", "silent")
    injection = report["injection"]
    assert injection["expected_safe_action"] == [0.1, 0.0]
    assert injection["safe_action"] == pytest.approx([0.1, 0.0], abs=4e-6)
    assert injection["safe_action_after_ms"] <= NODE_TIMEOUT_MS + SAFE_MARGIN_MS


def test_an_export_without_an_interface_is_a_clear_error(
    export_dir: Path, tmp_path: Path, capsys: pytest.CaptureFixture[str]
) -> None:
    old = tmp_path / "old-export"
    shutil.copytree(export_dir, old)
    (old / "interface.json").unlink()
    assert main(["hil", "run", "--export-dir", str(old), "--json", str(tmp_path / "x.json")]) == 2
    assert "no interface.json" in capsys.readouterr().err


def test_killed_node_ends_the_episode_as_a_fault_not_a_hang(
    guest: Guest, export_dir: Path, tmp_path: Path
) -> None:
    start = time.monotonic()
    report = _hil(guest, export_dir, tmp_path, "--episodes", "3", "--inject", "kill")
    assert time.monotonic() - start < 120
    assert report["injection"]["kind"] == "kill"
    assert report["faults"] == 1 and report["episodes"] == 1  # the session stops: the node is gone
    assert report["per_episode"][0]["fault"] == "the node exited with status -9"
    assert report["rx_timeouts"] == 1


def test_missing_export_folder_is_a_clear_error(tmp_path: Path, capsys: pytest.CaptureFixture[str]) -> None:
    assert main(["hil", "run", "--export-dir", str(tmp_path), "--json", str(tmp_path / "x.json")]) == 2
    assert "no c/policy.c" in capsys.readouterr().err


def test_realtime_with_a_watchdog_shorter_than_a_step_is_rejected(
    export_dir: Path, tmp_path: Path, capsys: pytest.CaptureFixture[str]
) -> None:
    code = main(
        [
            "hil",
            "run",
            "--export-dir",
            str(export_dir),
            "--json",
            str(tmp_path / "x.json"),
            "--realtime",
            "--timeout-ms",
            "200",
        ]
    )
    assert code == 2 and "must exceed the policy's sample time (300 ms)" in capsys.readouterr().err


def test_realtime_mode_reports_latency_jitter_and_deadline_misses(
    guest: Guest, export_dir: Path, tmp_path: Path
) -> None:
    # A report, not a verdict: timing inside User-Mode Linux is noisy, so only the shape is checked.
    report = _hil(guest, export_dir, tmp_path, "--episodes", "1", "--realtime", "--timeout-ms", "500")
    assert report["successes"] == 1 and report["max_action_abs_diff"] <= 1e-5
    assert isinstance(report["deadline_misses"], int)
    assert set(report["jitter_us"]) == {"std", "max_abs"}
    assert report["latency_us"]["max"] > 0


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
    _hil(guest, export_dir, tmp_path, "--episodes", "1")
    assert set(Path(tempfile.gettempdir()).glob("embedrl-hil-*")) == before
