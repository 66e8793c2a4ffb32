"""Processor in the loop: the CAN node as Cortex-M firmware on QEMU, bridged to the bus over SLCAN.

Fast: the instruction figures' parsing and the cycle model's classes (the serial framing's own unit tests
are C, in ``make -C runtime_c test``). Slow: the firmware node on the host over python-can's ``slcan``
interface alone (no kernel CAN), then lock-step episodes through ``vcan0`` in the sandbox on the M4F
(float32, int8-weights, q15) and the M3, and the node-side fault classes against the firmware.
"""

from __future__ import annotations

import json
import os
import re
import socket
import subprocess
import sys
import time
from collections.abc import Iterator
from contextlib import contextmanager
from pathlib import Path

import can
import numpy as np
import pytest

from embedrl.cli import main
from embedrl.export import cycles
from embedrl.export.build import RUNTIME_C
from embedrl.export.contract.interface_file import load_interface
from embedrl.export.contract.layout import STATUS_PERIOD_MS, WATCHDOG_MS, layout
from embedrl.export.reference import reference_policy
from embedrl.export.target import TARGETS
from embedrl.hil.codec import Action, Codec
from embedrl.hil.firmware import (
    FirmwareNode,
    HostQemu,
    instruction_summary,
    serve_qemu,
)
from embedrl.hil.link import Link, Stats
from embedrl.hil.sandbox import Guest
from tests.conftest import Exported
from tests.hil.conftest import SHIPPED_TD3
from tests.hil.helpers import hil

TOLERANCE = 1e-5
M4F_MACHINE = TARGETS["cortex-m4"].qemu_machine
NODE_FAULTS = (
    "corrupt", "replay", "delay", "out-of-range", "kill-restart", "replay-fresh", "silent", "loss", "flood",
)  # fmt: skip
"""The node-side fault classes (the catalogue's, less those acting on the kernel's interface)."""


def test_instruction_figures_come_from_the_timer_lines(tmp_path: Path) -> None:
    assert cycles.instructions_per_inference(
        ["STACK 52", "TICKS 298399 64 256", "DONE 256"], 40.0
    ) == pytest.approx((298399 - 64) * 40 / 256)
    with pytest.raises(Exception, match="TICKS"):
        cycles.instructions_per_inference(["DONE 256"], 1.0)
    node = FirmwareNode.__new__(FirmwareNode)  # the diagnostics files only: no QEMU
    node.diag, node.starts, node.tick_instructions = tmp_path / "uart1.txt", 2, 40.0
    (tmp_path / "uart1-0.txt").write_text("READY\nS 1 1250\nX 0 0\nS 2 1260\ngarbage\n")
    (tmp_path / "uart1-1.txt").write_text("READY\nS 1 1240\n")
    assert node.step_instructions() == [1250 * 40.0, 1260 * 40.0, 1240 * 40.0]
    summary = instruction_summary(node.step_instructions(), 40.0)
    assert summary is not None and summary["steps"] == 3 and summary["max"] == 1260 * 40.0
    assert summary["resolution"] == 40.0 and instruction_summary([], 1.0) is None
    assert TARGETS["cortex-m4"].tick_instructions == 1.0  # the STM32F405's TIM2: one tick per instruction


@pytest.mark.parametrize(
    ("mnemonic", "operands", "cls", "words"),
    [
        ("vfma.f32", "s15, s14, s13", "fp_multiply_accumulate", 0),
        ("vmul.f32", "s15, s14, s13", "fp_alu", 0),
        ("vldmia", "r3!, {s15}", "load_multiple", 1),
        ("vldmia", "r3!, {s16-s23}", "load_multiple", 8),  # the dot products' VLDM: 1 + 8 cycles
        ("vpush", "{d8-d9}", "store_multiple", 4),
        ("ldr.w", "r3, [r2, #4]", "load", 0),
        ("push", "{r4, r5, r6, lr}", "store_multiple", 4),
        ("pop", "{r4-r7, pc}", "load_multiple", 5),
        ("bne.n", "1c4", "branch", 0),
        ("bic", "r3, r3, #1", "alu", 0),
        ("umull", "r0, r1, r2, r3", "long_multiply", 0),
        ("mla", "r0, r1, r2, r3", "multiply_accumulate", 0),
    ],
)
def test_the_cycle_model_classes_instructions_as_the_manual_does(
    mnemonic: str, operands: str, cls: str, words: int
) -> None:
    assert cycles._classify(mnemonic) == cls
    if words:
        assert cycles._registers(operands) == words


def _firmware(export: Path, target: str, build: Path) -> Path:
    subprocess.run(
        ["make", "-s", "-C", str(RUNTIME_C), f"TARGET={target}", "node", f"POLICY_DIR={export / 'c'}",
         f"BUILD_DIR={build}"],
        check=True, capture_output=True, text=True,
    )  # fmt: skip
    return build / target / "node.elf"


@pytest.mark.slow
def test_the_firmware_answers_over_slcan_alone_as_the_reference_does(
    export_dir: Path, tmp_path: Path
) -> None:
    """The host's python-can ``slcan`` interface on the firmware's UART, no bus in between: 20 steps of
    random observations answered, each within the signals' resolution of the export's reference."""
    elf = _firmware(export_dir, "cortex-m4", tmp_path)
    qemu = subprocess.Popen(
        ["qemu-system-arm", "-M", M4F_MACHINE, "-nographic", "-monitor", "none", "-semihosting", "-serial",
         "pty", "-serial", f"file:{tmp_path / 'uart1.txt'}", "-icount", "shift=0", "-kernel", str(elf)],
        stdout=subprocess.PIPE, text=True,
    )  # fmt: skip
    try:
        assert qemu.stdout is not None
        pty = re.search(r"/dev/pts/\d+", qemu.stdout.readline())
        assert pty is not None
        _await_line(tmp_path / "uart1.txt", "LINK")  # its USART drops what comes before it is enabled
        bus = can.Bus(interface="slcan", channel=pty.group(0), sleep_after_open=0)
        interface = load_interface(export_dir / "interface.json")
        codec, reference = Codec(interface), reference_policy(export_dir)
        rng = np.random.default_rng(0)
        for step in range(1, 21):
            obs = np.array([rng.uniform(f.low, f.high) for f in interface.observation], np.float32)
            frames, sent = codec.encode_observation(obs, step)
            for frame in frames:
                bus.send(frame)
            answer = None
            for _ in range(100):
                decoded = codec.decode(bus.recv(0.1) or can.Message(arbitration_id=0x7FF))
                if isinstance(decoded, Action) and decoded.step == step:
                    answer = decoded
                    break
            assert answer is not None, f"step {step} unanswered"
            np.testing.assert_allclose(
                answer.action, reference(sent.reshape(1, -1)).reshape(-1), atol=TOLERANCE
            )
        bus.shutdown()
        # The step's line follows its action frame on the other UART: give the last one time to land.
        deadline = time.monotonic() + 10.0
        while _step_lines(tmp_path / "uart1.txt") < 20 and time.monotonic() < deadline:
            time.sleep(0.05)
    finally:
        qemu.kill()
        qemu.wait()
    lines = (tmp_path / "uart1.txt").read_text().splitlines()
    assert lines[:2] == ["LINK", "READY"] and _step_lines(tmp_path / "uart1.txt") == 20


@pytest.mark.slow
def test_the_host_runs_the_firmware_at_the_guests_request(export_dir: Path, tmp_path: Path) -> None:
    """The QEMU server a UML session uses, with a socket pair standing in for the guest's serial line:
    each start request boots a fresh image on this machine that answers an observation; a kill ends it
    at once, a stop in order once its diagnostics are written, and each exit is reported."""
    elf = _firmware(export_dir, "cortex-m4", tmp_path)
    link, guest_end = socket.socketpair()
    guest_end.settimeout(10.0)
    interface = load_interface(export_dir / "interface.json")
    codec = Codec(interface)
    obs = np.array([(f.low + f.high) / 2 for f in interface.observation], np.float32)
    emulator = HostQemu(tmp_path / "control", "/dev/ttyS1")
    with serve_qemu(str(elf), M4F_MACHINE, link, tmp_path / "control"):
        for start, in_order in enumerate((False, True)):
            guest_end.sendall(b"C\r" * 3)  # a closing bridge's lines, dropped before the next start
            assert emulator.start(tmp_path / f"uart1-{start}.txt") == "/dev/ttyS1" and emulator.alive()
            _await_line(tmp_path / f"uart1-{start}.txt", "LINK")
            codec.receivers.clear()  # a fresh image: its E2E counters start again
            frames, _ = codec.encode_observation(obs, 1)
            guest_end.sendall(b"O\r" + b"".join(_slcan(frame) for frame in frames))
            assert _answered_step(guest_end, codec) == 1
            if in_order:
                emulator.stop(tmp_path / f"uart1-{start}.txt")
            else:
                emulator.kill()
            assert not emulator.alive() and emulator.exit_status() == (0 if in_order else -9)
    assert _step_lines(tmp_path / "uart1-1.txt") == 1  # stopped in order: its last step's line written
    link.close()
    guest_end.close()


@pytest.mark.slow
def test_the_firmwares_watchdog_counts_the_simulations_time_not_the_hosts(
    export_dir: Path, tmp_path: Path
) -> None:
    """Steps a second apart on the host's clock (twice the 500 ms watchdog) but a sample time apart in the
    simulation's: every one answered, no timeout. Then the simulation's time goes on with no observation:
    the safe action at exactly the watchdog (a status period at a time, counted from the last observation)
    and one timeout in the node's status."""
    elf = _firmware(export_dir, "cortex-m4", tmp_path)
    interface = load_interface(export_dir / "interface.json")
    codec = Codec(interface)
    channel = f"pil-{tmp_path.name}"
    observation_ids = [frame_id for _, frame_id, _ in layout(interface).observation]
    harness = Link(
        can.Bus(interface="virtual", channel=channel, receive_own_messages=False),
        codec,
        Stats(),
        channel,
        None,
    )
    node = FirmwareNode(
        str(elf), M4F_MACHINE, lambda: can.Bus(interface="virtual", channel=channel),
        tmp_path / "uart1.txt", observation_ids,
    )  # fmt: skip
    obs = np.array([(f.low + f.high) / 2 for f in interface.observation], np.float32)
    try:
        for step in range(3):
            assert node.advance(interface.sample_time_s)
            harness.send(codec.encode_observation(obs, step)[0])
            assert harness.wait_action(step, time.monotonic() + 10.0) is not None, f"step {step} unanswered"
            time.sleep(2 * WATCHDOG_MS / 1000)  # the host falls behind
        quiet_ms, safe_at = 0, None
        while safe_at is None and quiet_ms < 2 * WATCHDOG_MS:
            assert node.advance(STATUS_PERIOD_MS / 1000)
            quiet_ms += STATUS_PERIOD_MS
            while (decoded := harness.receive(0.05)) is not False:
                if isinstance(decoded, Action) and np.allclose(decoded.action, interface.safe_action):
                    safe_at = quiet_ms
        status = harness.stats.last_status
    finally:
        node.kill()
        harness.close()
    assert safe_at == WATCHDOG_MS
    assert status is not None and status.timeouts == 1 and status.state == "SAFE"


def _await_line(diag: Path, word: str, timeout_s: float = 10.0) -> None:
    """Wait for the firmware's diagnostics line ``word`` (LINK: its link UART is enabled from then on)."""
    deadline = time.monotonic() + timeout_s
    while not (diag.is_file() and word in diag.read_text().split()):
        assert time.monotonic() < deadline, f"the firmware never said {word}"
        time.sleep(0.02)


def _slcan(frame: can.Message) -> bytes:
    return f"t{frame.arbitration_id:03X}{frame.dlc}{bytes(frame.data).hex().upper()}\r".encode()


def _answered_step(end: socket.socket, codec: Codec) -> int | None:
    """The step of the first action frame the firmware sends back on ``end``."""
    buffer = b""
    while True:
        buffer += end.recv(4096)
        *lines, buffer = buffer.split(b"\r")
        for line in lines:
            if line[:1] != b"t":
                continue
            frame = can.Message(
                arbitration_id=int(line[1:4], 16), data=bytes.fromhex(line[5:].decode()), is_extended_id=False
            )
            decoded = codec.decode(frame)
            if isinstance(decoded, Action):
                return decoded.step


def _step_lines(diag: Path) -> int:
    return sum(line.startswith("S ") for line in diag.read_text().splitlines())


M4F_INFERENCE = 26_000
"""Fewer instructions than one inference of the shipped TD3 on the M4F (26,659: docs/cortex-m.md): a node
step counts at least that."""


@pytest.fixture(scope="module")
def quantized_exports(exported: Exported) -> dict[str, Path]:
    return {p: exported(SHIPPED_TD3, "--episodes", "0", "--quantize", p) for p in ("int8-weights", "q15")}


@pytest.mark.slow
def test_three_lock_step_episodes_with_the_firmware_node_on_the_m4f(
    guest: Guest, export_dir: Path, tmp_path: Path
) -> None:
    report = hil(
        guest, export_dir, tmp_path, "--node", "firmware", "--target", "cortex-m4", "--episodes", "3"
    )
    assert report["node"] == "firmware" and report["target"] == "cortex-m4"
    assert report["successes"] == 3 and report["outcomes_differing_from_simulation"] == []
    assert report["max_action_abs_diff"] <= TOLERANCE
    # the firmware's node starts once the bridge has opened the channel: none of its frames is lost
    assert report["node_diag"]["send_failures"] == 0
    per_step = report["instructions_per_step"]
    assert per_step["steps"] == report["steps"]
    # the node cycle holds one inference (26,659 instructions on the M4F) plus decoding and encoding
    assert M4F_INFERENCE < per_step["mean"] < 2 * M4F_INFERENCE and per_step["max"] < 2 * per_step["mean"]
    timed = report["time_on_target"]  # the worst step at the modelled part's clock, against the sample time
    assert timed["clock"]["hz"] == 168_000_000 and timed["worst_step_instructions"] == per_step["max"]
    assert "STM32F405" in timed["clock"]["part"] and per_step["resolution"] == 1.0  # the image's part
    assert 1.0 < timed["cycles_per_instruction"] < 3.0
    step_s = timed["estimated_step_us"] / 1e6
    assert timed["margin_s"] == pytest.approx(timed["sample_time_s"] - step_s, abs=1e-5)
    assert 0 < timed["fraction_of_sample_time"] < 0.01
    # the painted stack (interrupts included) never exceeds the static bound of the same image
    firmware = report["firmware"]
    assert 0 < firmware["stack_peak_bytes"] <= firmware["stack_bound"]["bytes"] < 1024
    assert len(report["node_binary_sha256"]) == 64


@pytest.mark.slow
@pytest.mark.parametrize("precision", ["int8-weights", "q15"])
def test_quantized_policies_on_the_firmware_node_match_their_models(
    guest: Guest, quantized_exports: dict[str, Path], tmp_path: Path, precision: str
) -> None:
    report = hil(guest, quantized_exports[precision], tmp_path, "--node", "firmware", "--episodes", "1")
    assert report["precision"] == precision and report["successes"] == 1
    assert report["max_action_abs_diff"] <= TOLERANCE  # bit-exact model, then the signals' resolution


@pytest.mark.slow
def test_one_episode_with_the_firmware_node_on_the_m3(guest: Guest, export_dir: Path, tmp_path: Path) -> None:
    report = hil(
        guest, export_dir, tmp_path, "--node", "firmware", "--target", "cortex-m3", "--episodes", "1"
    )
    """The Cortex-M3 is an STM32F100RB on QEMU's stm32vldiscovery, its steps counted by SysTick at 24 MHz
    (125/3 instructions per tick); the channel opens before the node starts, so no frame is lost."""
    assert report["successes"] == 1 and report["max_action_abs_diff"] <= TOLERANCE
    per_step = report["instructions_per_step"]
    assert per_step["mean"] > 400_000  # software floating point: ~10x the M4F
    assert per_step["resolution"] == pytest.approx(125 / 3)
    timed = report["time_on_target"]
    assert timed["clock"]["hz"] == 24_000_000 and "STM32F100RB" in timed["clock"]["part"]
    assert report["firmware"]["stack_peak_bytes"] <= report["firmware"]["stack_bound"]["bytes"]
    assert report["node_diag"]["send_failures"] == 0


@contextmanager
def cpu_hogs() -> Iterator[None]:
    """A busy loop per core (a process each, at normal priority) while the block runs."""
    hogs = [subprocess.Popen([sys.executable, "-c", "while True: pass"]) for _ in range(os.cpu_count() or 1)]
    try:
        yield
    finally:
        for hog in hogs:
            hog.kill()
            hog.wait()


@pytest.mark.slow
def test_a_busy_host_changes_neither_the_verdict_nor_the_firmwares_steps(
    guest: Guest, export_dir: Path, tmp_path: Path
) -> None:
    """The firmware's clock is the simulation's: the same run on a quiet machine and with every core busy
    gives the same trajectory, the same actions, the same instructions at every step (within the timer's
    tick) and no watchdog timeout."""
    argv = ("--node", "firmware", "--episodes", "1", "--seed", "2")
    quiet = hil(guest, export_dir, tmp_path, *argv)
    with cpu_hogs():
        busy = hil(guest, export_dir, tmp_path, *argv)
    for report in (quiet, busy):
        assert report["successes"] == 1 and report["rx_timeouts"] == 0 and report["retries"] == 0
        assert report["node_status"]["timeouts"] == 0 and report["node_status"]["state"] == "RUN"
    assert busy["per_episode"] == quiet["per_episode"]  # trajectory, outcome, return
    assert busy["action_diffs"] == quiet["action_diffs"]  # the same actions for the same observations
    # Each step's count is read off the STM32F405's TIM2, one tick per instruction under QEMU: exact.
    steps = quiet["firmware"]["step_instructions"]
    assert len(steps) == quiet["steps"] > 5 and busy["firmware"]["step_instructions"] == steps
    assert min(steps) > M4F_INFERENCE


@pytest.mark.slow
def test_the_node_side_faults_are_detected_on_the_firmware_as_on_the_host_node(
    guest: Guest, export_dir: Path, tmp_path: Path
) -> None:
    inject = [a for i, kind in enumerate(NODE_FAULTS) for a in ("--inject", f"{kind}@{i}:3")]
    argv = ["--node", "firmware", "--episodes", str(len(NODE_FAULTS)), "--allow-faults", *inject]
    report = hil(guest, export_dir, tmp_path, *argv)
    assert {r["kind"] for r in report["injections"]} == set(NODE_FAULTS)
    for record in report["injections"]:
        assert record["detected"] is not False, record["kind"]
        assert record["answered_as_expected"], record["kind"]


def test_the_firmware_node_refuses_what_it_cannot_do_in_one_line(
    export_dir: Path, capsys: pytest.CaptureFixture[str]
) -> None:
    base = ["hil", "run", "--export-dir", str(export_dir), "--node", "firmware"]
    for extra, message in (
        (["--fd"], "drop --fd"),
        (["--nodes", "2"], "drop --nodes"),
        (["--kill-node", "1@0:3"], "drop --kill-node"),
        (["--inject", "link-down-up", "--allow-faults"], "only the C node has"),
        (["--timeout-ms", "300"], "must exceed the policy's sample time (300 ms)"),  # simulated time
    ):
        assert main([*base, *extra]) == 2
        err = capsys.readouterr().err.strip()
        assert message in err and len(err.splitlines()) == 1


def test_the_target_benchmark_refuses_without_its_peer_in_one_line(
    export_dir: Path, tmp_path: Path, capsys: pytest.CaptureFixture[str]
) -> None:
    argv = ["bench-target", "--export-dir", str(export_dir), "--emx", str(tmp_path / "nosuch")]
    assert main(argv) == 2
    err = capsys.readouterr().err.strip()
    assert "make bench-target" in err and len(err.splitlines()) == 1
    with pytest.raises(SystemExit) as refused:  # an unknown target: refused at parsing, with the choices
        main(["bench-target", "--export-dir", str(export_dir), "--target", "cortex-m0"])
    assert refused.value.code == 2
    err = capsys.readouterr().err.strip()
    assert "invalid choice: 'cortex-m0'" in err and "cortex-m4" in err and len(err.splitlines()) == 1


@pytest.mark.slow
def test_the_target_benchmark_measures_a_quantised_export_alone_with_its_cycles_per_multiply_add(
    quantized_exports: dict[str, Path], tmp_path: Path, capsys: pytest.CaptureFixture[str]
) -> None:
    out = tmp_path / "target.json"
    argv = ["bench-target", "--export-dir", str(quantized_exports["q15"]), "--target", "cortex-m4"]
    assert main([*argv, "--emx", str(tmp_path / "nosuch"), "--json", str(out)]) == 0  # no peer: not needed
    printed = capsys.readouterr().out
    assert "q15: measured alone" in printed and "emx_onnx_cgen" not in printed
    report = json.loads(out.read_text())
    assert report["peer"] is None and [t["target"] for t in report["targets"]] == ["cortex-m4"]
    ours = report["targets"][0]["embedrl"]
    assert ours["multiply_adds"] == 6 * 100 + 100 * 100 + 100 * 2  # the shipped TD3's actor
    per_mac = ours["estimated_cycles_per_inference"] / ours["multiply_adds"]
    assert ours["estimated_cycles_per_multiply_add"] == pytest.approx(per_mac, abs=0.005)
    assert f"({ours['estimated_cycles_per_multiply_add']})" in printed
