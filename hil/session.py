"""One HIL session: the simulator drives a policy node over a CAN bus, episode by episode.

Lock-step (the basis of every verdict): each step the simulator sends the observation frames, waits
for the node's action for that step, applies it and steps the physics; the exported ONNX policy runs
on the observation the node decoded and the difference is recorded. ``realtime`` paces the loop at the
interface's sample time and counts deadline misses (a report, not a verdict). The episodes are the
ordinary evaluation loop (:func:`embedrl.train.evaluate.run_episode`) with a policy that talks over the
bus; a step the node does not answer ends the episode as a fault.

Backends: ``node="c"`` runs the compiled node on SocketCAN (``bus="socketcan"``, the verdict);
``node="python"`` runs the reference node (:class:`~embedrl.hil.nodes.PythonNode`) in this process,
typically on python-can's virtual bus (``bus="virtual"``) for fast tests of the session logic.

Run as ``python -m embedrl.hil.session CONFIG.json``; it writes the results JSON named in the config.
"""

from __future__ import annotations

import json
import sys
import time
from dataclasses import asdict, dataclass
from pathlib import Path
from typing import Any

import can
import gymnasium as gym
import numpy as np
import onnxruntime as ort

from embedrl.hil import candb
from embedrl.hil.codec import Codec, Status
from embedrl.hil.faults import INJECT_STEP, INJECTORS, Context
from embedrl.hil.link import Link, Stats
from embedrl.hil.nodes import CNode, Node, PythonNode
from embedrl.train.evaluate import run_episode
from embedrl.train.interface import Interface

TOLERANCE = 1e-5
NODE_BOOT_S = 1.0
"""The node is up when its first status frame arrives (or after this long)."""


@dataclass(frozen=True)
class SessionConfig:
    onnx: str
    interface: str
    """The export's interface.json: the env, the CAN layout, the sample time and the safe action."""
    node_binary: str | None = None
    """The compiled ``policy_node`` (``node="c"``)."""
    node: str = "c"
    """``c`` (the compiled node, a process) or ``python`` (the reference node, a thread)."""
    bus: str = "socketcan"
    """python-can interface: ``socketcan`` or ``virtual``."""
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
    """A name in :data:`embedrl.hil.faults.INJECTORS`, or None."""


class NodeFault(Exception):
    """The node did not answer a step (or a fault was injected): the episode ends as a fault."""


class _Tally(gym.Wrapper[np.ndarray, np.ndarray, np.ndarray, np.ndarray]):
    """Steps and return so far: what a fault leaves of an episode that did not finish."""

    def reset(self, **kwargs: Any) -> tuple[np.ndarray, dict[str, Any]]:
        self.steps, self.total = 0, 0.0
        return self.env.reset(**kwargs)

    def step(self, action: np.ndarray) -> tuple[np.ndarray, float, bool, bool, dict[str, Any]]:
        obs, reward, terminated, truncated, info = self.env.step(action)
        self.steps, self.total = self.steps + 1, self.total + float(reward)
        return obs, float(reward), terminated, truncated, info


class BusPolicy:
    """A policy whose actions come from the node over the bus: the simulator's side of one step."""

    def __init__(self, cfg: SessionConfig, interface: Interface, link: Link, node: Node) -> None:
        self.cfg, self.interface, self.link, self.node = cfg, interface, link, node
        self.session = ort.InferenceSession(cfg.onnx, providers=["CPUExecutionProvider"])
        self.input = self.session.get_inputs()[0].name
        self.step = 0
        """Global step counter: the ``Step`` signal (mod 4096)."""
        self.episode = -1
        self.in_episode = 0
        self.next_tick = 0.0
        self.injection: dict[str, Any] | None = None

    def begin_episode(self) -> None:
        self.episode += 1
        self.in_episode = 0
        if self.cfg.realtime:
            self.link.stats.step_starts.append([])

    def __call__(self, obs: np.ndarray) -> np.ndarray:
        stats = self.link.stats
        frames, decoded = self.link.codec.encode_observation(obs, self.step)
        if self.cfg.inject and self.episode == 0 and self.in_episode == INJECT_STEP:
            injector = INJECTORS[self.cfg.inject]
            context = Context(
                self.link, self.node, self.interface, self.cfg.node_timeout_ms, self.cfg.action_timeout_s
            )
            self.injection = injector.apply(context, frames, self.step)
            if injector.ends_episode:
                raise NodeFault(f"injected: {injector.name}")
            frames, decoded = self.link.codec.encode_observation(obs, self.step)
        if self.cfg.realtime:
            self._pace()
        start = time.perf_counter_ns()
        sent_at = time.monotonic()
        self.link.send(frames)
        action = self.link.wait_action(self.step, self.cfg.action_timeout_s, self.node.alive)
        if action is None:
            stats.rx_timeouts += 1
            raise NodeFault(self._silence_reason(sent_at))
        stats.latencies_us.append((time.perf_counter_ns() - start) / 1000.0)
        reference = np.asarray(self.session.run(None, {self.input: decoded.reshape(1, -1)})[0]).reshape(-1)
        diff = float(np.max(np.abs(action.action.astype(np.float64) - reference)))
        stats.diffs.append(diff)
        if diff > TOLERANCE and stats.first_divergent_step is None:
            stats.first_divergent_step = self.step
        self.step += 1
        self.in_episode += 1
        return action.action

    def _pace(self) -> None:
        now = time.monotonic()
        if self.in_episode == 0:
            self.next_tick = now
        else:
            self.next_tick += self.interface.sample_time_s
            if now > self.next_tick:
                self.link.stats.deadline_misses += 1
            else:
                time.sleep(self.next_tick - now)
        self.link.stats.step_starts[-1].append(time.monotonic())

    def _silence_reason(self, since: float) -> str:
        if not self.node.alive():
            return self.node.exit_reason()
        if self.link.stats.last_status_time < since:
            return "no action and no status frame: the node stopped talking"
        return "no action for the step although the node still sends status"


def _start_node(cfg: SessionConfig, interface: Interface) -> Node:
    if cfg.node == "python":
        bus = can.Bus(interface=cfg.bus, channel=cfg.iface, receive_own_messages=False)
        return PythonNode(bus, interface, cfg.onnx, cfg.node_timeout_ms, cfg.node_recover)
    if cfg.node_binary is None:
        raise ValueError("the C node needs node_binary")
    return CNode(cfg.node_binary, cfg.iface, cfg.node_timeout_ms, cfg.node_recover)


def run(cfg: SessionConfig) -> dict[str, Any]:
    """Run the episodes; return the results (also written to cfg.results)."""
    interface = candb.load_interface(Path(cfg.interface))
    stats = Stats()
    bus = can.Bus(interface=cfg.bus, channel=cfg.iface, receive_own_messages=False)
    link = Link(bus, Codec(interface), stats, cfg.iface, cfg.log)
    node = _start_node(cfg, interface)
    policy = BusPolicy(cfg, interface, link, node)
    env = _Tally(gym.make(interface.env_id))
    episodes: list[dict[str, Any]] = []
    try:
        link.wait_status(NODE_BOOT_S)
        for index in range(cfg.episodes):
            seed = cfg.seed + index
            policy.begin_episode()
            try:
                result = run_episode(env, policy, seed, interface.sample_time_s)
                row = {**asdict(result), "fault": None}
            except NodeFault as fault:
                trajectory = list(getattr(env.unwrapped, "trajectory", []))
                row = {
                    "seed": seed,
                    "outcome": "fault",
                    "steps": env.steps,
                    "episode_return": env.total,
                    "time_s": env.steps * interface.sample_time_s,
                    "collided_with": None,
                    "trajectory": trajectory,
                    "fault": str(fault),
                }
            episodes.append(row)
            if row["fault"] and not node.alive():
                break  # the node is gone: later episodes could only fail the same way
        link.wait_status(0.3)
    finally:
        node.stop()
        link.close()
        env.close()
    results = _results(cfg, stats, episodes, policy.injection, interface.sample_time_s)
    Path(cfg.results).write_text(json.dumps(results, indent=2) + "\n")
    return results


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
