"""One HIL session where a vcan interface exists (on the host or inside User-Mode Linux).

Lock-step (the basis of every verdict): each step the simulator sends the observation frames, waits
for the node's action for that step, applies it and steps the physics; the exported ONNX policy
runs on the observation the node decoded and the difference is recorded. ``realtime`` paces the
loop at the env's sample time and counts deadline misses (a report, not a verdict).

Run as ``python -m embedrl.hil.session CONFIG.json``; it writes the results JSON named in the config.
"""

from __future__ import annotations

import json
import signal
import subprocess
import sys
import time
from dataclasses import asdict, dataclass, field
from pathlib import Path
from typing import Any

import can
import gymnasium as gym
import numpy as np
import onnxruntime as ort

from embedrl.hil import candb
from embedrl.hil.codec import STEP_MODULO, Action, Codec, Status
from embedrl.train.interface import Interface

INJECT_STEP = 3
"""Fault injections happen at this step of the first episode."""
TOLERANCE = 1e-5


@dataclass(frozen=True)
class SessionConfig:
    node: str
    onnx: str
    interface: str
    """The export's interface.json: the env, the CAN layout, the sample time and the safe action."""
    iface: str = "vcan0"
    episodes: int = 10
    seed: int = 0
    node_timeout_ms: int = candb.WATCHDOG_MS
    node_recover: int = 3
    action_timeout_s: float = 2.0
    realtime: bool = False
    log: str | None = None
    results: str = "hil_results.json"
    inject: str | None = None
    """None, "corrupt", "silent" or "kill" (see run())."""


@dataclass
class Stats:
    frames_tx: int = 0
    frames_rx: int = 0
    rx_timeouts: int = 0
    latencies_us: list[float] = field(default_factory=list)
    diffs: list[float] = field(default_factory=list)
    first_divergent_step: int | None = None
    deadline_misses: int = 0
    step_starts: list[list[float]] = field(default_factory=list)
    """Real time: when each step's observation went out (monotonic seconds), per episode."""
    last_status: Status | None = None
    last_status_time: float = 0.0


class Link:
    """The simulator's end of the bus: send observation frames, collect actions and status, log all."""

    def __init__(self, cfg: SessionConfig, interface: Interface, stats: Stats) -> None:
        self.bus = can.Bus(interface="socketcan", channel=cfg.iface, receive_own_messages=False)
        self.codec = Codec(interface)
        self.stats = stats
        self.log = can.Logger(cfg.log) if cfg.log else None
        self.iface = cfg.iface

    def send(self, frames: list[can.Message]) -> None:
        for frame in frames:
            frame.timestamp = time.time()
            frame.channel = self.iface
            frame.is_rx = False
            self.bus.send(frame)
            self.stats.frames_tx += 1
            if self.log:
                self.log(frame)

    def wait_action(self, step: int, timeout_s: float) -> Action | None:
        """Drain the socket until the action for ``step`` arrives or the timeout passes."""
        deadline = time.monotonic() + timeout_s
        while True:
            remaining = deadline - time.monotonic()
            if remaining <= 0:
                return None
            msg = self.bus.recv(timeout=remaining)
            if msg is None:
                return None
            self._received(msg)
            decoded = self.codec.decode(msg)
            if isinstance(decoded, Status):
                self.stats.last_status, self.stats.last_status_time = decoded, time.monotonic()
            elif isinstance(decoded, Action) and decoded.step == step % STEP_MODULO:
                return decoded

    def wait_status(self, timeout_s: float) -> Status | None:
        deadline = time.monotonic() + timeout_s
        while (remaining := deadline - time.monotonic()) > 0:
            msg = self.bus.recv(timeout=remaining)
            if msg is None:
                break
            self._received(msg)
            decoded = self.codec.decode(msg)
            if isinstance(decoded, Status):
                self.stats.last_status, self.stats.last_status_time = decoded, time.monotonic()
                return decoded
        return None

    def _received(self, msg: can.Message) -> None:
        # python-can flags frames from another local socket (the node) as Tx; they are received here.
        msg.is_rx = True
        msg.channel = self.iface
        self.stats.frames_rx += 1
        if self.log:
            self.log(msg)

    def close(self) -> None:
        if self.log:
            self.log.stop()
        self.bus.shutdown()


def _fault_reason(node: subprocess.Popen[bytes], stats: Stats, since: float) -> str:
    if node.poll() is not None:
        return f"the node exited with status {node.returncode}"
    if stats.last_status_time < since:
        return "no action and no status frame: the node stopped talking"
    return "no action for the step although the node still sends status"


def run(cfg: SessionConfig) -> dict[str, Any]:
    """Run the episodes; return the results (also written to cfg.results)."""
    stats = Stats()
    node = subprocess.Popen(
        [
            cfg.node,
            "--iface",
            cfg.iface,
            "--timeout-ms",
            str(cfg.node_timeout_ms),
            "--recover",
            str(cfg.node_recover),
        ],
        stdout=subprocess.DEVNULL,
        stderr=subprocess.PIPE,
    )
    interface = candb.load_interface(Path(cfg.interface))
    sample_time = interface.sample_time_s
    link = Link(cfg, interface, stats)
    session = ort.InferenceSession(cfg.onnx, providers=["CPUExecutionProvider"])
    input_name = session.get_inputs()[0].name
    env = gym.make(interface.env_id)
    episodes: list[dict[str, Any]] = []
    injection: dict[str, Any] | None = None
    global_step = 0
    try:
        link.wait_status(1.0)  # the node is up when its first status frame arrives
        for index in range(cfg.episodes):
            seed = cfg.seed + index
            obs, info = env.reset(seed=seed)
            total, steps, outcome, fault = 0.0, 0, "timeout", None
            trajectory = [tuple(env.unwrapped.trajectory[-1])]  # type: ignore[attr-defined]
            next_tick = time.monotonic()
            while True:
                frames, decoded = link.codec.encode_observation(obs, global_step)
                if cfg.inject and index == 0 and steps == INJECT_STEP:
                    injection = _inject(cfg, interface, link, node, frames, global_step, stats)
                    outcome, fault = "fault", f"injected: {cfg.inject}"
                    if cfg.inject != "kill":
                        break
                    frames, decoded = link.codec.encode_observation(obs, global_step)
                start = time.perf_counter_ns()
                sent_at = time.monotonic()
                if cfg.realtime:
                    if steps == 0:
                        stats.step_starts.append([])
                    stats.step_starts[-1].append(sent_at)
                link.send(frames)
                action = link.wait_action(global_step, cfg.action_timeout_s)
                if action is None:
                    stats.rx_timeouts += 1
                    outcome, fault = "fault", _fault_reason(node, stats, sent_at)
                    break
                stats.latencies_us.append((time.perf_counter_ns() - start) / 1000.0)
                reference = np.asarray(session.run(None, {input_name: decoded.reshape(1, -1)})[0]).reshape(-1)
                diff = float(np.max(np.abs(action.action.astype(np.float64) - reference)))
                stats.diffs.append(diff)
                if diff > TOLERANCE and stats.first_divergent_step is None:
                    stats.first_divergent_step = global_step
                obs, reward, terminated, truncated, info = env.step(action.action)
                total += float(reward)
                steps += 1
                global_step += 1
                trajectory.append(tuple(env.unwrapped.trajectory[-1]))  # type: ignore[attr-defined]
                if terminated or truncated:
                    outcome = (
                        "success"
                        if info.get("is_success")
                        else "collision"
                        if info.get("collided")
                        else "timeout"
                    )
                    break
                if cfg.realtime:
                    next_tick += sample_time
                    if time.monotonic() > next_tick:
                        stats.deadline_misses += 1
                    else:
                        time.sleep(next_tick - time.monotonic())
            episodes.append(
                {
                    "seed": seed,
                    "outcome": outcome,
                    "steps": steps,
                    "episode_return": total,
                    "time_s": steps * sample_time,
                    "fault": fault,
                    "trajectory": trajectory,
                }
            )
            if fault and node.poll() is not None:
                break  # the node is gone: later episodes could only fail the same way
        link.wait_status(0.3)
    finally:
        if node.poll() is None:
            node.send_signal(signal.SIGTERM)
            try:
                node.wait(timeout=5)
            except subprocess.TimeoutExpired:
                node.kill()
        link.close()
        env.close()
    results = _results(cfg, stats, episodes, injection, sample_time)
    Path(cfg.results).write_text(json.dumps(results, indent=2) + "\n")
    return results


def _inject(
    cfg: SessionConfig,
    interface: Interface,
    link: Link,
    node: subprocess.Popen[bytes],
    frames: list[can.Message],
    step: int,
    stats: Stats,
) -> dict[str, Any]:
    """Apply the configured fault at this step; return what was observed."""
    if cfg.inject == "corrupt":
        before = link.wait_status(1.0)
        bad = bytearray(frames[1].data)
        bad[4] ^= 0x10  # one bit of the payload: the CRC no longer matches
        frames[1].data = bad
        link.send(frames)
        action = link.wait_action(step, min(cfg.action_timeout_s, 3 * cfg.node_timeout_ms / 1000))
        after = link.wait_status(1.0)
        return {
            "kind": "corrupt",
            "action_received": action is not None,
            "node_crc_errors_before": before.crc_errors if before else None,
            "node_crc_errors_after": after.crc_errors if after else None,
        }
    if cfg.inject == "silent":
        last_sent = time.monotonic()
        deadline = last_sent + 5.0
        safe_after_ms, safe_seen = None, None
        while time.monotonic() < deadline:
            msg = link.bus.recv(timeout=deadline - time.monotonic())
            if msg is None:
                break
            stats.frames_rx += 1
            decoded = link.codec.decode(msg)
            if isinstance(decoded, Status):
                stats.last_status = decoded
            if isinstance(decoded, Action) and _is_safe(decoded.action, interface):
                safe_after_ms = (time.monotonic() - last_sent) * 1000
                safe_seen = decoded.action.tolist()
                break
        status = link.wait_status(1.0)
        return {
            "kind": "silent",
            "safe_action_after_ms": safe_after_ms,
            "safe_action": safe_seen,
            "expected_safe_action": list(interface.safe_action),
            "node_timeout_ms": cfg.node_timeout_ms,
            "node_state": status.state if status else None,
        }
    if cfg.inject == "kill":
        node.kill()
        node.wait()
        return {"kind": "kill", "node_exit": node.returncode}
    raise ValueError(f"unknown injection {cfg.inject!r}")


def _is_safe(action: np.ndarray, interface: Interface) -> bool:
    """Whether ``action`` is the interface's safe action, within the CAN quantisation."""
    step = max(slot.scale for slot in candb.layout(interface).action_slots)
    return bool(np.max(np.abs(action - np.asarray(interface.safe_action))) <= step)


def _results(
    cfg: SessionConfig, stats: Stats, episodes: list[dict[str, Any]], injection: Any, sample_time: float
) -> dict[str, Any]:
    lat = np.array(stats.latencies_us) if stats.latencies_us else np.zeros(1)
    status = stats.last_status
    return {
        "episodes": episodes,
        "steps": int(sum(e["steps"] for e in episodes)),
        "max_action_abs_diff": max(stats.diffs) if stats.diffs else None,
        "first_divergent_step": stats.first_divergent_step,
        "frames_tx": stats.frames_tx,
        "frames_rx": stats.frames_rx,
        "crc_errors": link_errors(status, "crc_errors"),
        "sequence_errors": link_errors(status, "sequence_errors"),
        "rx_timeouts": stats.rx_timeouts,
        "latency_us": {
            "p50": float(np.percentile(lat, 50)),
            "p99": float(np.percentile(lat, 99)),
            "max": float(lat.max()),
        },
        "latencies_us": stats.latencies_us,
        "deadline_misses": stats.deadline_misses if cfg.realtime else None,
        "jitter_us": _jitter(stats.step_starts, sample_time) if cfg.realtime else None,
        "node_status": asdict(status) if status else None,
        "injection": injection,
        "config": asdict(cfg),
    }


def _jitter(starts: list[list[float]], sample_time: float) -> dict[str, float] | None:
    """Deviation of the real-time step period from the sample time: std and max, in microseconds.

    Periods are measured within episodes: a reset is not a control period.
    """
    periods = np.concatenate([np.diff(np.array(episode)) for episode in starts]) if starts else np.zeros(0)
    if len(periods) == 0:
        return None
    deviation = (periods - sample_time) * 1e6
    return {"std": float(np.std(deviation)), "max_abs": float(np.max(np.abs(deviation)))}


def link_errors(status: Status | None, key: str) -> int | None:
    """Errors the node counted (from its last status frame)."""
    return None if status is None else int(getattr(status, key))


if __name__ == "__main__":
    config = SessionConfig(**json.loads(Path(sys.argv[1]).read_text()))
    run(config)
