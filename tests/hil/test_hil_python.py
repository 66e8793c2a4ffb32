"""The HIL contract against the Python reference node on python-can's virtual bus: no kernel, no build.

Every session-logic path (lock-step, faults, the safe action, real-time pacing) runs here in seconds;
the same suite runs against the compiled node over SocketCAN in ``test_hil_vcan.py``.
"""

from __future__ import annotations

import json
import os
import resource
import shutil
import signal
import subprocess
import sys
import time
import types
from dataclasses import fields
from pathlib import Path

import can
import numpy as np
import onnx
import pytest
from onnx import helper, numpy_helper

from embedrl.cli import build_parser, main
from embedrl.export.contract.interface_file import load_interface
from embedrl.export.reference import reference_policy
from embedrl.hil.codec import Action, Codec, Status
from embedrl.hil.errors import HilError
from embedrl.hil.node_kinds import NODE_KINDS
from embedrl.hil.nodes import PythonNode
from embedrl.hil.options import RunOptions
from embedrl.hil.run import check
from tests.hil.contract import HilContract
from tests.test_user_errors import run_and_interrupt


class TestPythonNodeOnVirtualBus(HilContract):
    node = "python"
    sandboxes = ("none",)
    channel = "embedrl-"

    def lying_export(self, export_dir: Path, tmp_path: Path) -> Path:
        """The ONNX's actions multiplied by NaN: the Python node runs the ONNX."""
        lying = tmp_path / "lying"
        shutil.copytree(export_dir, lying)
        model = onnx.load(lying / "policy.onnx")
        graph = model.graph
        output = graph.output[0].name
        graph.initializer.append(numpy_helper.from_array(np.array([np.nan], dtype=np.float32), "nan"))
        for node in graph.node:
            node.output[:] = [f"{o}_honest" if o == output else o for o in node.output]
        graph.node.append(helper.make_node("Mul", [f"{output}_honest", "nan"], [output]))
        onnx.save(model, lying / "policy.onnx")
        return lying


def test_an_export_without_an_interface_is_a_clear_error(
    export_dir: Path, tmp_path: Path, capsys: pytest.CaptureFixture[str]
) -> None:
    old = tmp_path / "old-export"
    shutil.copytree(export_dir, old)
    (old / "interface.json").unlink()
    assert main(["hil", "run", "--export-dir", str(old), "--json", str(tmp_path / "x.json")]) == 2
    assert "no interface.json" in capsys.readouterr().err


@pytest.mark.parametrize("node", ["c", "firmware"])
def test_hand_edited_c_is_refused_before_anything_is_built_or_run(
    node: str, export_dir: Path, tmp_path: Path, capsys: pytest.CaptureFixture[str]
) -> None:
    """An export's C that is not the generator's output (here with a constructor that would write a file on
    the host) is neither built nor run by hil run, unless --trust-c says the user trusts it."""
    edited = tmp_path / "edited export"
    shutil.copytree(export_dir, edited)
    marker = tmp_path / "ran"
    with (edited / "c" / "policy.c").open("a") as source:
        source.write(
            f"\n#include <stdio.h>\n__attribute__((constructor)) static void payload(void)\n{{\n"
            f'    FILE *f = fopen("{marker}", "w");\n'
            "    if (f != NULL) {\n        (void)fclose(f);\n    }\n}\n"
        )
    argv = ["hil", "run", str(edited), "--node", node, "--episodes", "1", "--json", str(tmp_path / "x.json")]
    assert main(argv) == 2
    err = capsys.readouterr().err.strip()
    assert "policy.c is not what embedrl generates from policy.onnx" in err and "--trust-c" in err
    assert len(err.splitlines()) == 1 and not marker.exists() and not (tmp_path / "x.json").exists()


def test_missing_export_folder_is_a_clear_error(tmp_path: Path, capsys: pytest.CaptureFixture[str]) -> None:
    assert main(["hil", "run", "--export-dir", str(tmp_path), "--json", str(tmp_path / "x.json")]) == 2
    assert "no c/policy.c" in capsys.readouterr().err


def test_keep_work_keeps_the_temporary_folder_and_names_it(
    export_dir: Path, tmp_path: Path, capsys: pytest.CaptureFixture[str]
) -> None:
    argv = [
        "hil",
        "run",
        "--export-dir",
        str(export_dir),
        "--json",
        str(tmp_path / "h.json"),
        "--node",
        "python",
    ]
    assert main([*argv, "--episodes", "1", "--keep-work"]) == 0
    line = next(x for x in capsys.readouterr().out.splitlines() if x.startswith("kept the node build"))
    kept = Path(line.rsplit(" in ", 1)[1])
    assert (kept / "results.json").is_file()
    shutil.rmtree(kept)


@pytest.mark.parametrize("sig", [signal.SIGTERM, signal.SIGINT])
def test_an_interrupted_hil_run_leaves_nothing_behind(
    sig: signal.Signals, export_dir: Path, tmp_path: Path
) -> None:
    (tmp_path / "tmp").mkdir()  # TMPDIR of the command
    report = str(tmp_path / "h.json")
    argv = [
        "hil",
        "run",
        "--export-dir",
        str(export_dir),
        "--json",
        report,
        "--node",
        "python",
        "--episodes",
        "200",
    ]
    done = run_and_interrupt(argv, tmp_path, "running 200 episode(s)", sig)
    assert done.returncode == 128 + sig and done.stderr.strip().splitlines()[-1] == "interrupted", done.stderr
    assert not (tmp_path / "h.json").exists()
    assert not [p for p in (tmp_path / "tmp").iterdir() if p.name.startswith("embedrl")]  # no work folder


def test_a_fault_scheduled_beyond_the_episode_limit_is_refused_up_front(
    export_dir: Path, tmp_path: Path, capsys: pytest.CaptureFixture[str]
) -> None:
    argv = ["hil", "run", "--export-dir", str(export_dir), "--json", str(tmp_path / "x.json")]
    assert main([*argv, "--node", "python", "--inject", "corrupt@0:5000"]) == 2
    err = capsys.readouterr().err
    assert "end by step 200, so the fault could never fire" in err and len(err.strip().splitlines()) == 1
    assert not (tmp_path / "x.json").exists()


def test_a_fault_whose_episode_ends_before_its_step_fails_the_run(export_dir: Path, tmp_path: Path) -> None:
    # Episode 0 of seed 0 ends (success) after 24 steps: a fault at step 150 never fires.
    out = tmp_path / "x.json"
    argv = ["hil", "run", "--export-dir", str(export_dir), "--json", str(out), "--node", "python"]
    assert main([*argv, "--inject", "corrupt@0:150", "--allow-faults", "--seed", "0"]) == 1
    report = json.loads(out.read_text())
    assert report["per_episode"][0]["steps"] < 150 and report["injections"] == []
    assert report["injections_not_fired"] == ["corrupt@0:150"]
    assert report["verdict"]["failures"] == [
        "fault corrupt@0:150 never fired: its episode ended before that step"
    ]


def test_the_summary_prints_the_nodes_own_counters(
    export_dir: Path, tmp_path: Path, capsys: pytest.CaptureFixture[str]
) -> None:
    # A delayed step trips the node's watchdog once: the summary says so, as the node's status does.
    out = tmp_path / "x.json"
    argv = ["hil", "run", "--export-dir", str(export_dir), "--json", str(out), "--node", "python"]
    assert main([*argv, "--inject", "delay", "--allow-faults", "--timeout-ms", "200"]) == 0
    report = json.loads(out.read_text())
    rows = dict(line.split("  ", 1) for line in capsys.readouterr().out.splitlines() if "  " in line)
    status = report["node_status"]
    assert status["timeouts"] == 1
    assert rows["node CRC / sequence errors / watchdog timeouts"].strip() == (
        f"{status['crc_errors']} / {status['sequence_errors']} / {status['timeouts']}"
    )
    assert rows["steps the node left unanswered"].strip() == str(report["rx_timeouts"])
    p99_ms, diag = report["latency_us"]["p99"] / 1000, report["node_diag"]
    assert rows["link: retries / stale steps / send failures / round trip p99"].strip() == (
        f"{report['retries']} / {diag['stale_steps']} / {diag['send_failures']} / "
        f"{p99_ms:.3g} ms (within the 0.3 s sample time)"
    )


def test_the_links_health_names_a_round_trip_above_the_sample_time() -> None:
    from embedrl.hil.verdict import link_health

    run = {"retries": 3, "node_status": {"timeouts": 0}, "node_diag": {"stale_steps": 3, "send_failures": 2},
           "latency_us": {"p99": 378_000.0}, "sample_time_s": 0.3}  # fmt: skip
    assert dict(link_health(run, 0.3)) == {
        "retries": "3", "stale steps": "3", "send failures": "2",
        "round trip p99": "378 ms (above the 0.3 s sample time)",
    }  # fmt: skip


def test_a_delay_is_held_until_a_node_with_a_slow_clock_times_out(
    export_dir: Path, tmp_path: Path, monkeypatch: pytest.MonkeyPatch
) -> None:
    """The watchdog runs on the node's clock, which can run behind the host's (the firmware's instruction-
    counted time on a loaded machine): the delayed step is held until the node reports its timeout."""
    real = time.monotonic
    origin = real()
    slow = types.SimpleNamespace(
        monotonic=lambda: origin + (real() - origin) * 0.4, perf_counter_ns=time.perf_counter_ns
    )
    monkeypatch.setattr("embedrl.hil.nodes.time", slow)  # the node's clock at 0.4x the host's
    out = tmp_path / "x.json"
    argv = ["hil", "run", "--export-dir", str(export_dir), "--json", str(out), "--node", "python"]
    assert main([*argv, "--inject", "delay", "--allow-faults", "--timeout-ms", "200"]) == 0
    record = json.loads(out.read_text())["injections"][0]
    assert record["detected"] and record["answer_is_safe_action"]
    assert 200 / 0.4 <= record["held_ms"] < 10 * 200  # beyond 1.5 timeouts on the host's clock (300 ms)


def test_the_python_node_counts_a_late_frame_as_a_timeout_as_the_c_node_does(export_dir: Path) -> None:
    """A step handled after the watchdog deadline with no poll in between (a busy node): SAFE, the timeout
    counted and the step answered with the safe action (``runtime_c/tests/test_node.c`` checks the C)."""
    interface = load_interface(export_dir / "interface.json")
    node = PythonNode(
        lambda: can.Bus(interface="virtual", channel="late-frame"), interface, reference_policy(export_dir),
        timeout_ms=500, recover=3,
    )  # fmt: skip
    node.stop()  # driven by hand below: no thread polls in between
    node.bus = can.Bus(interface="virtual", channel="late-frame")
    listener = can.Bus(interface="virtual", channel="late-frame")
    codec = Codec(interface)
    obs = np.array([(f.low + f.high) / 2 for f in interface.observation], np.float32)
    for step, now in ((1, 100.0), (2, 100.0 + 0.501)):
        for frame in codec.encode_observation(obs, step)[0]:
            node._on_frame(frame, now)
    assert node.state == "SAFE" and node.counts["timeouts"] == 1
    sent = list(iter(lambda: listener.recv(0.2), None))
    actions = [a for a in map(codec.decode, sent) if isinstance(a, Action)]
    assert [a.step for a in actions][-1] == 2
    np.testing.assert_array_equal(actions[-1].action, np.asarray(interface.safe_action, np.float32))
    node.bus.shutdown()
    listener.shutdown()


def test_policy_node_help_is_an_answer_not_an_error(export_dir: Path, tmp_path: Path) -> None:
    from embedrl.export import build

    build.make("node", export_dir / "c", tmp_path)
    asked = subprocess.run([str(tmp_path / "policy_node"), "--help"], capture_output=True, text=True)
    assert asked.returncode == 0 and asked.stdout.startswith("usage: policy_node --iface NAME")
    wrong = subprocess.run([str(tmp_path / "policy_node"), "--bogus"], capture_output=True, text=True)
    assert wrong.returncode == 2 and wrong.stderr.startswith("usage: policy_node")


def test_a_session_reports_its_episodes_and_the_host_draws_them(
    export_dir: Path, tmp_path: Path, capsys: pytest.CaptureFixture[str], monkeypatch: pytest.MonkeyPatch
) -> None:
    """The session rewrites its progress file after each episode; on a terminal ``hil run`` draws a bar from
    it (what shows progress while the session runs inside a guest), and nothing when not a terminal."""
    from embedrl.hil.progress import episode_bar, read_done
    from embedrl.hil.session import SessionConfig, run

    progress = tmp_path / "progress"
    cfg = SessionConfig(
        onnx=str(export_dir / "policy.onnx"), interface=str(export_dir / "interface.json"), node="python",
        bus="virtual", iface="embedrl-progress", episodes=3, results=str(tmp_path / "r.json"),
        progress=str(progress),
    )  # fmt: skip
    run(cfg)
    assert progress.read_text() == "3 3\n" and read_done(tmp_path / "nosuch") == 0
    capsys.readouterr()
    monkeypatch.setattr("sys.stderr.isatty", lambda: True)
    with episode_bar(progress, 3):
        pass
    assert "HIL episodes: 100%" in capsys.readouterr().err and "3/3" in progress.read_text().replace(" ", "/")
    assert main(["hil", "run", "--export-dir", str(export_dir), "--node", "python", "--episodes", "2",
                 "--json", str(tmp_path / "h.json")]) == 0  # fmt: skip
    assert "HIL episodes: 100%" in capsys.readouterr().err
    monkeypatch.setattr("sys.stderr.isatty", lambda: False)
    assert main(["hil", "run", "--export-dir", str(export_dir), "--node", "python", "--episodes", "2",
                 "--json", str(tmp_path / "h.json")]) == 0  # fmt: skip
    assert "HIL episodes" not in capsys.readouterr().err


def test_the_python_node_says_start_until_its_first_step_and_resets_on_safe_as_the_c_node_does(
    export_dir: Path,
) -> None:
    """NodeStatus's START: the policy at zero state (start-up or a reset), no step answered since
    (``runtime_c/tests/test_node.c`` checks the C)."""
    interface = load_interface(export_dir / "interface.json")
    node = PythonNode(
        lambda: can.Bus(interface="virtual", channel="start-state"), interface, reference_policy(export_dir),
        timeout_ms=500, recover=3,
    )  # fmt: skip
    node.stop()
    node.bus = can.Bus(interface="virtual", channel="start-state")
    listener = can.Bus(interface="virtual", channel="start-state")
    codec = Codec(interface)

    def state_now() -> str:
        node._send_status()
        statuses = [
            s for s in map(codec.decode, iter(lambda: listener.recv(0.2), None)) if isinstance(s, Status)
        ]
        return statuses[-1].state

    assert state_now() == "START"
    obs = np.array([(f.low + f.high) / 2 for f in interface.observation], np.float32)
    for frame in codec.encode_observation(obs, 1)[0]:
        node._on_frame(frame, 100.0)
    assert state_now() == "RUN"
    node._check_watchdog(100.0 + 0.5)
    assert node.state == "SAFE" and node.fresh and state_now() == "SAFE"
    node.bus.shutdown()
    listener.shutdown()


def _with_read_only(folder: Path, argv: list[str]) -> list[str]:
    """``argv`` run with ``folder`` read-only: for root (whom a folder's mode does not stop), in a mount
    namespace of its own where the folder is a read-only bind mount; for others, the folder's mode."""
    if os.geteuid() != 0:
        folder.chmod(0o555)
        return argv
    mount = 'mount --bind "$0" "$0" && mount -o remount,ro,bind "$0" "$0" && exec "$@"'
    probe = subprocess.run(["unshare", "-m", "sh", "-c", mount, str(folder), "true"], capture_output=True)
    if probe.returncode != 0:
        pytest.skip(f"no mount namespace here: {probe.stderr.decode().strip()}")
    return ["unshare", "-m", "sh", "-c", mount, str(folder), *argv]


def test_a_report_for_a_read_only_export_is_refused_before_the_run(export_dir: Path, tmp_path: Path) -> None:
    # The report's link goes into the export's chain.json at the end: a folder that cannot take it is
    # refused before the run, not after a whole run that then leaves no link.
    export = tmp_path / "export"
    shutil.copytree(export_dir, export)
    report = tmp_path / "hil.json"
    argv = [sys.executable, "-m", "embedrl.cli", "hil", "run", "--export-dir", str(export),
            "--node", "python", "--episodes", "3", "--json", str(report)]  # fmt: skip
    before = resource.getrusage(resource.RUSAGE_CHILDREN)
    try:
        result = subprocess.run(_with_read_only(export, argv), capture_output=True, text=True, timeout=300)
    finally:
        export.chmod(0o755)
    after = resource.getrusage(resource.RUSAGE_CHILDREN)
    # the child's CPU time, not wall time: another job's share of a busy machine stretches the latter
    cpu_s = after.ru_utime + after.ru_stime - before.ru_utime - before.ru_stime
    lines = result.stderr.strip().splitlines()
    assert result.returncode == 2 and len(lines) == 1 and "is not writable" in lines[0], result.stderr[-2000:]
    assert not report.exists() and cpu_s < 10, f"{cpu_s:.1f} s of CPU"


GIVEN = {
    "sandbox": "host", "target": "cortex-m3", "fd": True, "nodes": 2, "kill_node": (1, 0, 3), "trust_c": True,
    "coverage": Path("hil.coverage"),
}  # fmt: skip
"""A value other than the default for each option some node kind refuses."""


@pytest.mark.parametrize(
    ("node", "option"), [(node, option) for node, kind in NODE_KINDS.items() for option in kind.refuses]
)
def test_an_option_that_does_not_apply_to_the_node_kind_is_refused(node: str, option: str) -> None:
    options = RunOptions(Path("unused"), node=node, episodes=2, **{option: GIVEN[option]})  # type: ignore[arg-type]
    with pytest.raises(HilError, match=f"--{option.replace('_', '-')} does not apply to --node {node}"):
        check(options)


def test_every_node_kind_is_an_option_of_hil_run_and_refuses_only_run_options() -> None:
    names = {f.name for f in fields(RunOptions)}
    for node, kind in NODE_KINDS.items():
        assert set(kind.refuses) <= names and set(kind.refuses) <= set(GIVEN)
        assert build_parser().parse_args(["hil", "run", "--export-dir", "x", "--node", node]).node == node
