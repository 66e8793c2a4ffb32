"""The policy node behind one interface: the compiled C node as a process, or a Python reference node.

:class:`PythonNode` follows the C node's rules (``runtime_c/node/node.c``) frame for frame: E2E checks
(CRC, alive counter with re-synchronisation), each signal's range, an observation only from frames of
one step, steps that do not go forward never answered, the watchdog with the interface's safe action,
recovery after K valid observations, NodeStatus and NodeDiag every
:data:`~embedrl.hil.STATUS_PERIOD_MS`, a bus filter for its own IDs. Its policy is the exported
export's policy at its precision (the ONNX under onnxruntime, or the model of the int8 or q15 arithmetic
the C equals bit for bit). It runs in a thread on any python-can bus, so the session logic is tested on
python-can's virtual bus in milliseconds; the C node over SocketCAN gives the verdict.
"""

from __future__ import annotations

import os
import signal
import subprocess
import threading
import time
from abc import ABC, abstractmethod
from collections.abc import Callable

import can
import numpy as np
from cantools.database.can.c_source import camel_to_snake_case

from embedrl.export.contract.dbc import database
from embedrl.export.contract.e2e import COUNTER_MODULO
from embedrl.export.contract.layout import (
    DIAG_COUNTERS,
    FRAME_BYTES,
    STATUS_PERIOD_MS,
    STEP_MODULO,
    episode_start_id,
    layout,
    scale_of,
)
from embedrl.hil import e2e
from embedrl.hil.codec import decode_fields
from embedrl.train.evaluate import start_episode
from embedrl.train.interface import Interface

STOP_TIMEOUT_S = 5.0
PROFILE_VARIABLE = "LLVM_PROFILE_FILE"
"""Where a node built with clang's coverage flags writes its raw profile when it exits."""
U8_MAX, U16_MAX, INFERENCE_US_MAX = 255, 65535, 1023


def action_ok(action: np.ndarray, interface: Interface) -> bool:
    """Every value finite and inside its field's range widened by half the signal's resolution,
    compared in float32 (``policy_io_action_ok``): the only actions a node sends besides the safe one."""
    values = np.asarray(action, dtype=np.float32).reshape(-1)
    if values.shape != (len(interface.action),) or not np.all(np.isfinite(values)):
        return False
    bounds = [(f.low - scale_of(f) / 2, f.high + scale_of(f) / 2) for f in interface.action]
    return all(np.float32(lo) <= v <= np.float32(hi) for (lo, hi), v in zip(bounds, values, strict=True))


class PolicyNode(ABC):
    """A running policy node."""

    simulated_time: bool = False
    """Whether the node's clock (its watchdog, its status period) runs in the simulation's time, moved only
    by :meth:`advance` (the firmware node), rather than in real time (the C and the Python node)."""

    def advance(self, seconds: float) -> bool:
        """Let ``seconds`` of the simulation's time pass for the node; True once it has acted on them (every
        frame the new time made it send is on the bus). A node on a real clock needs nothing: False."""
        return False

    @abstractmethod
    def alive(self) -> bool: ...

    @abstractmethod
    def exit_reason(self) -> str:
        """Why it is gone (for a fault message)."""

    @abstractmethod
    def kill(self) -> None:
        """End it at once, as a crash would."""

    @abstractmethod
    def stop(self) -> None:
        """End it in order."""

    @abstractmethod
    def restart(self) -> None:
        """Start it again after it died (a fresh node: all its state from the beginning)."""


class CNode(PolicyNode):
    """``policy_node --iface IFACE --timeout-ms T --recover K`` as a child process."""

    def __init__(
        self,
        binary: str,
        iface: str,
        timeout_ms: int,
        recover: int,
        node_id: int = 0,
        profile: str | None = None,
    ) -> None:
        """The binary was built for classic CAN or CAN FD (``make node FD=1``); it knows which. ``profile``:
        its ``LLVM_PROFILE_FILE`` (a node built for coverage writes its profile there when it exits)."""
        self.argv = [binary, "--iface", iface, "--timeout-ms", str(timeout_ms), "--recover", str(recover),
                     "--node-id", str(node_id)]  # fmt: skip
        self.env = {**os.environ, PROFILE_VARIABLE: profile} if profile is not None else None
        self.process = self._start()

    def _start(self) -> subprocess.Popen[bytes]:
        # its stderr: the session log
        return subprocess.Popen(self.argv, stdout=subprocess.DEVNULL, env=self.env)

    def restart(self) -> None:
        self.stop()
        self.process = self._start()

    def alive(self) -> bool:
        return self.process.poll() is None

    def exit_reason(self) -> str:
        return f"the node exited with status {self.process.returncode}"

    def kill(self) -> None:
        self.process.kill()
        self.process.wait()

    def stop(self) -> None:
        if self.process.poll() is None:
            self.process.send_signal(signal.SIGTERM)
            try:
                self.process.wait(timeout=STOP_TIMEOUT_S)
            except subprocess.TimeoutExpired:
                self.process.kill()


class PythonNode(PolicyNode):
    """The reference node: the C node's rules in Python, the exported ONNX as the policy."""

    def __init__(
        self,
        open_bus: Callable[[], can.BusABC],
        interface: Interface,
        policy: Callable[[np.ndarray], np.ndarray],
        timeout_ms: int,
        recover: int,
        node_id: int = 0,
        fd: bool = False,
    ) -> None:
        self.open_bus = open_bus
        self.interface = interface
        self.db = database(interface, node_id, fd)
        self.plan = layout(interface, node_id, fd)
        self.policy = policy
        self.timeout_s = timeout_ms / 1000
        self.recover = recover
        self.safe = np.asarray(interface.safe_action, dtype=np.float32)
        self.obs_ids = [frame_id for _, frame_id, _ in self.plan.observation]
        self.episode_start_id = episode_start_id(node_id) if interface.state_size else None
        self._start()

    def _start(self) -> None:
        """All state from the beginning, a new bus and thread (as a freshly started node)."""
        self.bus = self.open_bus()
        try:
            self._prepare()
        except BaseException:  # interrupted while starting: the bus is not left open
            self.bus.shutdown()
            raise

    def _prepare(self) -> None:
        listen = [*self.obs_ids, *([self.episode_start_id] if self.episode_start_id is not None else [])]
        self.bus.set_filters([{"can_id": i, "can_mask": 0x7FF, "extended": False} for i in listen])
        self.rx = {frame_id: e2e.Receiver() for frame_id in listen}
        self._reset_policy()  # a started node's policy has zero state
        self.tx_counters: dict[int, int] = {}
        self.state = "RUN"
        self.counts = dict.fromkeys(
            (
                "frames_ok", "crc_errors", "sequence_errors", "timeouts", "range_errors", "action_faults",
                "resyncs", "stale_steps", "incomplete",
            ),
            0,
        )  # fmt: skip
        self.inference_us = 0
        self.pending_step: int | None = None
        self.pending_parts: set[int] = set()
        self.pending_obs = np.zeros(len(self.interface.observation), dtype=np.float32)
        self.armed = False
        self.consecutive_valid = 0
        self.last_step = 0
        self.step_reference = False
        now = time.monotonic()
        self.last_valid = self.last_safe = self.next_status = now
        self._stop = threading.Event()
        self._killed = False
        self.thread = threading.Thread(target=self._run, name="python-node", daemon=True)
        self.thread.start()

    def restart(self) -> None:
        self.stop()
        self._start()

    def alive(self) -> bool:
        return self.thread.is_alive()

    def exit_reason(self) -> str:
        return "the node exited (the Python node was killed)" if self._killed else "the node exited"

    def kill(self) -> None:
        self._killed = True
        self._stop.set()
        self.thread.join()

    def stop(self) -> None:
        self._stop.set()
        self.thread.join()

    def _run(self) -> None:
        try:
            while not self._stop.is_set():
                wait = self._poll(time.monotonic())
                msg = self.bus.recv(timeout=min(wait, 0.05))
                if msg is not None and not self._stop.is_set():
                    self._on_frame(msg, time.monotonic())
        finally:
            self.bus.shutdown()

    def _send(self, name: str, fields: dict[str, float]) -> None:
        message = self.db.get_message_by_name(name)
        counter = self.tx_counters.get(message.frame_id, 0)
        self.tx_counters[message.frame_id] = (counter + 1) % COUNTER_MODULO
        data = message.encode({"Crc": 0, "Counter": counter, **fields}, scaling=True, strict=False)
        self.bus.send(
            can.Message(
                arbitration_id=message.frame_id,
                data=e2e.protect(message.frame_id, data),
                is_extended_id=False,
                is_fd=message.is_fd,
            )
        )

    def _send_action(self, action: np.ndarray, step: int) -> None:
        for name, _, slots in self.plan.action:
            values = {}
            for s in slots:  # checked by action_ok (or the safe action): at most rounding to the bound
                values[s.signal] = min(max(float(action[s.index]), s.field.low), s.field.high)
            self._send(name, {"Step": step, **values})

    def _action_ok(self, action: np.ndarray) -> bool:
        return action_ok(action, self.interface)

    def _send_status(self) -> None:
        self._send(
            "NodeStatus",
            {
                "State": 1 if self.state == "SAFE" else 2 if self.fresh else 0,
                "FramesOk": min(self.counts["frames_ok"], U16_MAX),
                "CrcErrors": min(self.counts["crc_errors"], U8_MAX),
                "SequenceErrors": min(self.counts["sequence_errors"], U8_MAX),
                "Timeouts": min(self.counts["timeouts"], U8_MAX),
                "InferenceUs": min(self.inference_us, INFERENCE_US_MAX),
            },
        )
        diag: dict[str, float] = {"BusState": 0}  # python-can's virtual bus has no controller
        for name, bits, _ in DIAG_COUNTERS:
            diag[name] = min(self.counts.get(camel_to_snake_case(name), 0), 2**bits - 1)
        self._send("NodeDiag", diag)

    def _check_watchdog(self, now: float) -> None:
        """No valid observation for the timeout while running -> SAFE (as ``check_watchdog``)."""
        if self.armed and self.state == "RUN" and now - self.last_valid >= self.timeout_s:
            self.counts["timeouts"] += 1
            self.state, self.consecutive_valid, self.last_safe = "SAFE", 0, now
            self._reset_policy()  # the safe state forgets the policy's memory
            self.step_reference = False  # a sender that comes back may have restarted its steps
            self._send_action(self.safe, self.last_step)
            self._send_status()

    def _poll(self, now: float) -> float:
        """Watchdog and status; the seconds until the next deadline (as ``node_poll``)."""
        if self.state == "SAFE" and min(now - self.last_safe, now - self.last_valid) >= self.timeout_s:
            self.last_safe = now
            self._send_action(self.safe, self.last_step)
        self._check_watchdog(now)  # after the refresh: entering SAFE sends the safe action itself
        if now >= self.next_status:
            self._send_status()
            self.next_status = now + STATUS_PERIOD_MS / 1000
        return max(0.0, min(self.next_status - now, self.timeout_s))

    def _on_frame(self, msg: can.Message, now: float) -> None:
        self._check_watchdog(now)  # a frame handled after the deadline is late, polled or not
        if msg.arbitration_id == self.episode_start_id and not msg.is_extended_id:
            self._on_episode_start(msg)
            return
        if msg.is_extended_id or msg.arbitration_id not in self.rx or msg.dlc != self.plan.frame_bytes:
            return  # not an observation frame: the C node counts it as rejected
        data = bytes(msg.data)
        if not e2e.crc_ok(msg.arbitration_id, data):
            self.counts["crc_errors"] += 1
            self.consecutive_valid = 0
            return
        message = self.db.get_message_by_frame_id(msg.arbitration_id)
        fields = decode_fields(message, data)
        verdict = self.rx[msg.arbitration_id].check(int(fields["Counter"]))
        if verdict != "ok":
            self.counts["sequence_errors"] += 1
            self.consecutive_valid = 0
        if verdict == "resync":
            self.counts["resyncs"] += 1
            self.step_reference = False  # a new sequence: its steps may start anywhere
        if verdict in ("repeated", "wrong_sequence"):
            return
        slots = self.plan.observation[self.obs_ids.index(msg.arbitration_id)][2]
        if any(
            not (s.field.low - s.scale / 2 <= fields[s.signal] <= s.field.high + s.scale / 2) for s in slots
        ):
            self.counts["range_errors"] += 1
            self.consecutive_valid = 0
            return
        self.counts["frames_ok"] += 1
        step = int(fields["Step"])
        if self.pending_step != step:
            self.counts["incomplete"] += bool(self.pending_parts)
            self.pending_step, self.pending_parts = step, set()  # never mix frames of two steps
        for s in slots:
            self.pending_obs[s.index] = fields[s.signal]
        self.pending_parts.add(msg.arbitration_id)
        if len(self.pending_parts) == len(self.obs_ids):
            self._complete(step, now)

    def _on_episode_start(self, msg: can.Message) -> None:
        """An E2E-valid EpisodeStart resets the policy's state (as ``node_on_frame``)."""
        data = bytes(msg.data)
        if msg.dlc != FRAME_BYTES or not e2e.crc_ok(msg.arbitration_id, data):
            self.counts["crc_errors"] += 1
            return
        fields = decode_fields(self.db.get_message_by_frame_id(msg.arbitration_id), data)
        verdict = self.rx[msg.arbitration_id].check(int(fields["Counter"]))
        if verdict in ("repeated", "wrong_sequence"):
            self.counts["sequence_errors"] += 1
            return
        self._reset_policy()

    def _reset_policy(self) -> None:
        """The policy's recurrent state to zero; the status says START until the next step (as the C)."""
        start_episode(self.policy)
        self.fresh = True

    def _complete(self, step: int, now: float) -> None:
        self.pending_step, self.pending_parts = None, set()
        ahead = (step - self.last_step) % STEP_MODULO
        if self.step_reference and not 0 < ahead < STEP_MODULO // 2:
            self.counts["stale_steps"] += 1  # a replayed or repeated step: never answered twice
            self.consecutive_valid = 0
            return
        self.step_reference = True
        self.last_valid, self.armed = now, True
        self.consecutive_valid += 1
        if self.state == "SAFE" and self.consecutive_valid >= self.recover:
            self.state = "RUN"
        if self.state == "SAFE":
            action = self.safe
        else:
            start = time.perf_counter_ns()
            out = np.asarray(self.policy(self.pending_obs.reshape(1, -1))).reshape(-1)
            self.fresh = False
            self.inference_us = (time.perf_counter_ns() - start) // 1000
            action = out.astype(np.float32)
            if not self._action_ok(action):
                # the node never acts on numbers it did not check: the safe action, SAFE, counted
                self.counts["action_faults"] += 1
                self.state, self.consecutive_valid, self.last_safe = "SAFE", 0, now
                self._reset_policy()
                self._send_action(self.safe, step)
                self._send_status()
                self.last_step = step
                return
        self._send_action(action, step)
        self.last_step = step
