"""The HIL contract: one test suite, run against every node backend (as python-can's back-to-back tests).

A backend is a subclass that says how ``embedrl hil run`` reaches its node (:meth:`HilContract.run_hil`):
the Python reference node on python-can's virtual bus (milliseconds, no kernel) or the compiled C node
over SocketCAN vcan0 in a sandbox (the verdict). The assertions are the same for both.
"""

from __future__ import annotations

import time
from pathlib import Path
from typing import Any, ClassVar

import pytest

from embedrl.cli import main
from embedrl.export.contract.dbc import database
from embedrl.export.contract.interface_file import load_interface
from embedrl.hil.codec import decode_fields
from embedrl.hil.faults import CATALOGUE, INJECT_STEP, INJECTORS
from embedrl.hil.sandbox import Guest
from embedrl.train.evaluate import REPORT_KEYS
from tests.hil.helpers import hil, hil_report

NODE_TIMEOUT_MS = 200
SAFE_MARGIN_MS = 200
"""Allowed lateness of the safe action beyond the watchdog timeout (scheduling in a guest, polling)."""
RECOVERED = (
    "loss", "burst", "duplicate", "replay", "replay-fresh", "reorder", "corrupt", "masquerade",
    "out-of-range", "flood", "kill-restart", "sender-restart",
)  # fmt: skip
"""Fault classes after which the episode goes on exactly as in the simulation."""


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

    def lying_export(self, export_dir: Path, tmp_path: Path) -> Path:
        """A copy of ``export_dir`` whose policy gives NaN actions while reporting success."""
        raise NotImplementedError

    lying_flags: ClassVar[tuple[str, ...]] = ()
    """What ``hil run`` needs to run the lying export (C edited by hand: ``--trust-c``)."""

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
        assert (
            report["frames_tx"] == 3 * (report["steps"] + report["retries"])
            and report["frames_rx"] >= report["steps"]
        )
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
        assert all(line.split()[2][:4] in ("200#", "300#", "301#") for line in received)  # Action, status
        diag = report["node_diag"]
        assert diag["bus_state"] == "ACTIVE" and diag["resyncs"] == diag["range_errors"] == 0
        assert diag["action_faults"] == diag["send_failures"] == diag["link_resets"] == 0
        assert diag["stale_steps"] <= report["retries"]  # a retry of a slow answer is a repeated step
        assert (tmp_path / "plots" / "hil_latency.png").is_file()
        assert (tmp_path / "plots" / "hil_trajectories.png").is_file()
        assert (tmp_path / "plots" / "hil_action_diff.png").is_file()
        diffs = report["action_diffs"]["0"]  # every step's difference, the run's maximum among them
        assert len(diffs) == report["steps"] and max(diffs) == report["max_action_abs_diff"]

    def test_the_fault_catalogue_is_detected_and_recovered_from(
        self, where: Guest | None, export_dir: Path, tmp_path: Path
    ) -> None:
        kinds = [i.name for i in CATALOGUE if not i.ends_episode and i.answered]
        kinds = [k for k in kinds if self.node == "c" or not INJECTORS[k].needs_socketcan]
        schedule = [arg for e, k in enumerate(kinds) for arg in ("--inject", f"{k}@{e}:{INJECT_STEP}")]
        report = self.run_hil(
            where, export_dir, tmp_path, "--episodes", str(len(kinds)), "--seed", "0", "--allow-faults",
            # the default watchdog: a 200 ms one can trip between two steps of a loaded machine and put
            # safe actions into an episode that must equal the simulation
            "--timeout-ms", "500",
            *schedule,
        )  # fmt: skip
        records = {r["kind"]: r for r in report["injections"]}
        assert list(records) == kinds
        assert report["fault_catalogue"] == {
            k: {
                "injected": 1,
                "detected": None if INJECTORS[k].detects is None else 1,
                "answered_as_expected": 1,
            }
            for k in kinds
        }
        for kind, r in records.items():
            injector = INJECTORS[kind]
            assert r["detected"] is (None if injector.detects is None else True), kind
            assert r["answered"] and r["answers_to_the_step"] == 1, kind  # never answered twice
        # Recovered without a trace in the episode: same outcome as the simulation, the policy's actions
        for kind in RECOVERED:
            row = report["per_episode"][kinds.index(kind)]
            assert row["injected"] == [kind] and row["fault"] is None, kind
            assert row["max_action_abs_diff"] <= 1e-5, kind
            assert row["seed"] not in report["outcomes_differing_from_simulation"], kind
            assert records[kind]["answer_is_safe_action"] is False or kind == "sender-restart", kind
        # Timed out or link lost: the late step is answered with the safe action, as the node is SAFE
        for kind in ("delay", *(["link-down-up"] if self.node == "c" else [])):
            assert records[kind]["answer_is_safe_action"] is True, kind
        assert records["delay"]["after"]["timeouts"] == records["delay"]["before"]["timeouts"] + 1
        assert (
            records["duplicate"]["after"]["sequence_errors"]
            >= records["duplicate"]["before"]["sequence_errors"] + 3
        )
        assert records["burst"]["after"]["resyncs"] == records["burst"]["before"]["resyncs"] + 3
        assert (
            records["out-of-range"]["after"]["range_errors"]
            == records["out-of-range"]["before"]["range_errors"] + 1
        )
        assert records["flood"]["flood_frames"] > 100
        if self.node == "c":
            assert records["bus-off"]["bus_state_when_passive"] == "PASSIVE"
            assert records["bus-off"]["after"]["bus_state"] == "BUS_OFF"
            assert records["bus-off"]["bus_state_after_restart"] == "ACTIVE"
        assert report["verdict"]["passed"], report["verdict"]

    def test_silent_simulator_gets_the_safe_action_within_the_timeout(
        self, where: Guest | None, export_dir: Path, tmp_path: Path
    ) -> None:
        report = self.run_hil(
            where, export_dir, tmp_path, "--episodes", "1", "--inject", "silent", "--allow-faults"
        )
        (injection,) = report["injections"]
        assert injection["safe_action_after_ms"] is not None
        assert NODE_TIMEOUT_MS * 0.9 <= injection["safe_action_after_ms"] <= NODE_TIMEOUT_MS + SAFE_MARGIN_MS
        assert injection["after"]["state"] == "SAFE" and injection["detected"] is True
        assert injection["expected_safe_action"] == [0.0, 0.0] and injection["safe_action"] == [0.0, 0.0]
        assert report["per_episode"][0]["fault"] == "injected: silent"

    def test_the_watchdog_sends_the_exports_own_safe_action(
        self, where: Guest | None, safe_export_dir: Path, tmp_path: Path
    ) -> None:
        # An export with --safe-action 0.1,0: the node's watchdog must send (0.1, 0), not zeros.
        report = self.run_hil(
            where, safe_export_dir, tmp_path, "--episodes", "1", "--inject", "silent", "--allow-faults"
        )
        (injection,) = report["injections"]
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
        (injection,) = report["injections"]
        assert injection["kind"] == "kill" and injection["detected"] is True and not injection["answered"]
        assert report["faults"] == 1 and report["episodes"] == 1  # the session stops: the node is gone
        assert report["per_episode"][0]["fault"].startswith("the node exited")
        assert report["per_episode"][0]["fault"] == injection["node_exit"]
        assert report["rx_timeouts"] == 1
        assert report["verdict"] == {"passed": True, "failures": [], "faults_allowed": True}

    def test_a_fault_fails_the_run_unless_faults_are_allowed(
        self, where: Guest | None, export_dir: Path, tmp_path: Path
    ) -> None:
        report = hil_report(where, export_dir, "--node", self.node, "--episodes", "2", "--inject", "kill")
        assert report["verdict"]["passed"] is False  # `embedrl hil run` exits 1 (test_hil_python.py)
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

    def test_a_policy_that_reports_success_with_nan_actions_gets_the_safe_action(
        self, where: Guest | None, safe_export_dir: Path, tmp_path: Path
    ) -> None:
        # The node checks the numbers, not the status: never (-1, -1) (NaN saturated), only (0.1, 0).
        lying = self.lying_export(safe_export_dir, tmp_path)
        log = tmp_path / "frames.log"
        argv = ["--log", str(log), "--node", self.node, "--episodes", "1", "--timeout-ms", "500",
                *self.lying_flags]  # fmt: skip
        report = hil_report(where, lying, *argv)
        assert report["verdict"]["passed"] is False
        assert report["node_diag"]["action_faults"] >= report["steps"] // 3  # SAFE, then K = 3 to recover
        interface = load_interface(lying / "interface.json")
        db = database(interface)
        action = db.get_message_by_name("Action")
        answers = [
            decode_fields(action, bytes.fromhex(line.split()[2].split("#")[1]))
            for line in log.read_text().splitlines()
            if line.endswith(" R") and line.split()[2].startswith(f"{action.frame_id:03X}#")
        ]
        assert len(answers) >= report["steps"] > 0
        for answer in answers:
            assert answer["ForceLeft"] == pytest.approx(0.1, abs=4e-6) and answer["ForceRight"] == 0.0
