"""The HIL contract: one test suite, run against every node backend (as python-can's back-to-back tests).

A backend is a subclass that says how ``embedrl hil run`` reaches its node (:meth:`HilContract.run_hil`):
the Python reference node on python-can's virtual bus (milliseconds, no kernel) or the compiled C node
over SocketCAN vcan0 in a sandbox (the verdict). The assertions are the same for both.
"""

from __future__ import annotations

import json
import time
from pathlib import Path
from typing import Any, ClassVar

import pytest

from embedrl.cli import build_parser, main
from embedrl.hil.cli import cmd_run
from embedrl.hil.sandbox import Guest
from embedrl.train.evaluate import REPORT_KEYS
from tests.hil.helpers import hil

NODE_TIMEOUT_MS = 200
SAFE_MARGIN_MS = 200
"""Allowed lateness of the safe action beyond the watchdog timeout (scheduling in a guest, polling)."""


class HilContract:
    node: ClassVar[str]
    """``--node`` of the backend."""
    sandboxes: ClassVar[tuple[str, ...]]
    """What the report's ``sandbox`` may say."""
    channel: ClassVar[str]
    """How the channel names in the frame log begin."""

    @pytest.fixture
    def where(self) -> Guest | None:
        """The guest the C node runs in (None: the Python node runs in the test process)."""
        return None

    def run_hil(self, where: Guest | None, export_dir: Path, tmp_path: Path, *extra: str) -> dict[str, Any]:
        return hil(
            where, export_dir, tmp_path, "--node", self.node, "--timeout-ms", str(NODE_TIMEOUT_MS), *extra
        )

    def test_lock_step_episodes_equal_the_simulation(
        self, where: Guest | None, export_dir: Path, tmp_path: Path
    ) -> None:
        log = tmp_path / "frames.log"
        report = self.run_hil(
            where, export_dir, tmp_path, "--episodes", "4", "--seed", "0", "--log", str(log),
            "--plot", str(tmp_path / "plots"),
        )  # fmt: skip
        assert report["sandbox"] in self.sandboxes
        assert report["episodes"] == 4 and report["faults"] == 0
        assert report["successes"] == report["simulation"]["successes"] == 4
        assert report["verdict"] == {"passed": True, "failures": [], "faults_allowed": False}
        assert report["outcomes_differing_from_simulation"] == []
        assert report["max_action_abs_diff"] <= 1e-5 and report["first_divergent_step"] is None
        assert report["frames_tx"] == 3 * report["steps"] and report["frames_rx"] >= report["steps"]
        assert report["crc_errors"] == 0 and report["sequence_errors"] == 0 and report["rx_timeouts"] == 0
        assert 0 < report["latency_us"]["p50"] <= report["latency_us"]["p99"] <= report["latency_us"]["max"]
        assert all(key in report for key in REPORT_KEYS)
        assert all(row["collided_with"] is None for row in report["per_episode"])
        lines = log.read_text().splitlines()
        assert len(lines) == report["frames_tx"] + report["frames_rx"]
        sent = [line for line in lines if line.endswith(" T")]
        received = [line for line in lines if line.endswith(" R")]
        assert len(sent) == report["frames_tx"] and len(received) == report["frames_rx"]
        assert all(line.split()[1].startswith(self.channel) for line in lines)
        assert all(line.split()[2][:3] in ("100", "101", "102") for line in sent)  # ObservationA..C
        assert all(line.split()[2][:4] in ("200#", "300#") for line in received)  # Action, NodeStatus
        assert (tmp_path / "plots" / "hil_latency.png").is_file()
        assert (tmp_path / "plots" / "hil_trajectories.png").is_file()

    def test_corrupted_observation_frame_is_dropped_and_counted(
        self, where: Guest | None, export_dir: Path, tmp_path: Path
    ) -> None:
        report = self.run_hil(
            where, export_dir, tmp_path, "--episodes", "1", "--inject", "corrupt", "--allow-faults"
        )
        injection = report["injection"]
        assert injection["kind"] == "corrupt"
        assert injection["action_received"] is False  # no action computed from the corrupted observation
        assert injection["node_crc_errors_after"] == injection["node_crc_errors_before"] + 1
        assert report["per_episode"][0]["fault"] == "injected: corrupt"

    def test_silent_simulator_gets_the_safe_action_within_the_timeout(
        self, where: Guest | None, export_dir: Path, tmp_path: Path
    ) -> None:
        report = self.run_hil(
            where, export_dir, tmp_path, "--episodes", "1", "--inject", "silent", "--allow-faults"
        )
        injection = report["injection"]
        assert injection["safe_action_after_ms"] is not None
        assert NODE_TIMEOUT_MS * 0.9 <= injection["safe_action_after_ms"] <= NODE_TIMEOUT_MS + SAFE_MARGIN_MS
        assert injection["node_state"] == "SAFE"
        assert injection["expected_safe_action"] == [0.0, 0.0] and injection["safe_action"] == [0.0, 0.0]

    def test_the_watchdog_sends_the_exports_own_safe_action(
        self, where: Guest | None, safe_export_dir: Path, tmp_path: Path
    ) -> None:
        # An export with --safe-action 0.1,0: the node's watchdog must send (0.1, 0), not zeros.
        report = self.run_hil(
            where, safe_export_dir, tmp_path, "--episodes", "1", "--inject", "silent", "--allow-faults"
        )
        injection = report["injection"]
        assert injection["expected_safe_action"] == [0.1, 0.0]
        assert injection["safe_action"] == pytest.approx([0.1, 0.0], abs=4e-6)
        assert injection["safe_action_after_ms"] <= NODE_TIMEOUT_MS + SAFE_MARGIN_MS

    def test_killed_node_ends_the_episode_as_a_fault_not_a_hang(
        self, where: Guest | None, export_dir: Path, tmp_path: Path
    ) -> None:
        start = time.monotonic()
        report = self.run_hil(
            where, export_dir, tmp_path, "--episodes", "3", "--inject", "kill", "--allow-faults"
        )
        assert time.monotonic() - start < 120
        assert report["injection"]["kind"] == "kill"
        assert report["faults"] == 1 and report["episodes"] == 1  # the session stops: the node is gone
        assert report["per_episode"][0]["fault"].startswith("the node exited")
        assert report["per_episode"][0]["fault"] == report["injection"]["node_exit"]
        assert report["rx_timeouts"] == 1
        assert report["verdict"] == {"passed": True, "failures": [], "faults_allowed": True}

    def test_a_fault_fails_the_run_unless_faults_are_allowed(
        self, where: Guest | None, export_dir: Path, tmp_path: Path
    ) -> None:
        out = tmp_path / "hil.json"
        argv = ["hil", "run", "--export-dir", str(export_dir), "--json", str(out), "--node", self.node]
        args = build_parser().parse_args([*argv, "--episodes", "2", "--inject", "kill"])
        assert cmd_run(args, where) == 1  # a script or CI can tell a failed HIL run from a good one
        report = json.loads(out.read_text())
        assert report["verdict"]["passed"] is False
        assert report["verdict"]["failures"][0].startswith("1 episode(s) ended in a fault (seeds [0])")

    def test_realtime_mode_reports_latency_jitter_and_deadline_misses(
        self, where: Guest | None, export_dir: Path, tmp_path: Path
    ) -> None:
        # A report, not a verdict: timing in a guest is noisy, so only the shape is checked.
        report = self.run_hil(
            where, export_dir, tmp_path, "--episodes", "1", "--realtime", "--timeout-ms", "500"
        )
        assert report["successes"] == 1 and report["max_action_abs_diff"] <= 1e-5
        assert isinstance(report["deadline_misses"], int)
        assert set(report["jitter_us"]) == {"std", "max_abs"}
        assert report["latency_us"]["max"] > 0
        steps = report["steps"]
        assert report["per_episode"][0]["time_s"] == pytest.approx(steps * 0.3)

    def test_realtime_with_a_watchdog_shorter_than_a_step_is_rejected(
        self, export_dir: Path, tmp_path: Path, capsys: pytest.CaptureFixture[str]
    ) -> None:
        argv = ["hil", "run", "--export-dir", str(export_dir), "--json", str(tmp_path / "x.json")]
        code = main([*argv, "--node", self.node, "--realtime", "--timeout-ms", "200"])
        assert code == 2 and "must exceed the policy's sample time (300 ms)" in capsys.readouterr().err
        assert not (tmp_path / "x.json").exists()
