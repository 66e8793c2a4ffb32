"""One HIL session: the simulator drives a policy node over a CAN bus, episode by episode.

Lock-step (the basis of every verdict): each step the simulator sends the observation frames, waits
for the node's action for that step, applies it and steps the physics, and records the observation the
node decoded with its action; once the episodes are over the export's reference runs on those
observations and the differences go into the results (:mod:`embedrl.hil.compare`; here, or on the host
for a session in a guest). A step not answered within
:data:`RETRY_S` (or half the node's watchdog, if shorter) is sent again with fresh E2E counters, as a
cyclic sender would, until ``action_timeout_s``; a node never answers a step twice. ``realtime`` paces
the loop at the interface's sample time and counts deadline misses (a report, not a verdict). The
episodes are the ordinary evaluation loop (:func:`embedrl.train.evaluate.run_episode`) with a policy that
talks over the bus; a step the node does not answer ends the episode as a fault.

Backends: ``node="c"`` runs the compiled node on SocketCAN (``bus="socketcan"``, the verdict);
``node="python"`` runs the reference node (:class:`~embedrl.hil.nodes.PythonNode`) in this process,
typically on python-can's virtual bus (``bus="virtual"``) for fast tests of the session logic.

Run as ``python -m embedrl.hil.session CONFIG.json``; it writes the results JSON named in the config.
"""

from __future__ import annotations

import json
import sys
import time
from collections.abc import Callable, Iterator
from contextlib import ExitStack, contextmanager
from dataclasses import asdict, dataclass
from pathlib import Path
from typing import Any

import can
import gymnasium as gym
import numpy as np

from embedrl.export.contract.interface_file import load_interface
from embedrl.export.contract.layout import (
    STATUS_PERIOD_MS,
    STEP_MODULO,
    WATCHDOG_MS,
)
from embedrl.hil import compare
from embedrl.hil.codec import Action, Codec, Diag, Status
from embedrl.hil.faults import Context, Injector, Scheduled, is_safe, parse_schedule
from embedrl.hil.firmware import FirmwareNode, instruction_summary
from embedrl.hil.link import Link, Stats
from embedrl.hil.node_kinds import DEFAULT_NODE, NODE_KINDS
from embedrl.hil.nodes import PolicyNode
from embedrl.train.evaluate import EpisodeResult, episode_result, run_episode
from embedrl.train.interface import NO_ENV, Interface

TOLERANCE = compare.TOLERANCE
NODE_BOOT_S = 1.0
"""The node is up when its first status frame arrives (or after this long)."""
RETRY_S = 0.25
"""An unanswered step is sent again after this long (or half the node's watchdog, if shorter)."""
NODE_SEED_STRIDE = 10_000
"""With several nodes, robot ``k``'s episode ``i`` is seeded ``seed + i + k * NODE_SEED_STRIDE``."""
OPEN_LOOP_STEPS = 100
"""Observations per open-loop episode."""
SNAPSHOT_S = 1.0
"""How long to wait for the node's status after an injection, if none came while the episode ran."""
LAST_STATUS_S = 0.3
"""How long to wait for the node's last status when the session ends."""
STATUS_PERIOD_S = STATUS_PERIOD_MS / 1000


@dataclass(frozen=True)
class SessionConfig:
    onnx: str
    interface: str
    """The export's interface.json: the env, the CAN layout, the sample time and the safe action."""
    export_dir: str | None = None
    """The export folder: the node's actions are compared with its reference for the export's precision
    (:func:`embedrl.export.reference.reference_policy`); None: with ``onnx`` under onnxruntime."""
    node_binary: str | None = None
    """The compiled ``policy_node`` (``node="c"``), or the firmware image (``node="firmware"``)."""
    node: str = DEFAULT_NODE
    """The node's kind, a name of :data:`embedrl.hil.node_kinds.NODE_KINDS` (its ``start`` starts it)."""
    qemu_machine: str | None = None
    """The board that runs the firmware image (``node="firmware"``), e.g. ``netduinoplus2``."""
    tick_instructions: float = 1.0
    """Guest instructions per tick of the firmware board's timer (its target's)."""
    firmware_link: str | None = None
    """The firmware node's QEMU runs on the host (:class:`embedrl.hil.firmware.HostQemu`): the guest's
    serial line to its UART0, e.g. ``/dev/ttyS1``; None: QEMU runs beside the session."""
    firmware_control: str | None = None
    """With ``firmware_link``: the folder of the requests to the host's QEMU server."""
    bus: str = "socketcan"
    """python-can interface: ``socketcan`` or ``virtual``."""
    iface: str = "vcan0"
    episodes: int = 10
    seed: int = 0
    node_timeout_ms: int = WATCHDOG_MS
    node_recover: int = 3
    action_timeout_s: float = 2.0
    realtime: bool = False
    log: str | None = None
    results: str = "hil_results.json"
    fd: bool = False
    """Observation and action frames in CAN FD (the C node built with ``FD=1``)."""
    nodes: int = 1
    """Nodes on the bus, one robot each (node ``k`` with its own IDs), driven in lock-step."""
    observations: str | None = None
    """Open loop (a policy exported without an env): the export's verification observations (.npy),
    replayed :data:`OPEN_LOOP_STEPS` per episode."""
    inject: tuple[str, ...] = ()
    """The fault schedule: ``NAME`` or ``NAME@EPISODE:STEP`` (:func:`embedrl.hil.faults.parse_schedule`)."""
    progress: str | None = None
    """A file rewritten after each episode with ``DONE TOTAL`` (the host draws a bar from it while the session
    runs in a guest: :func:`embedrl.hil.progress.episode_bar`)."""
    kill_node: tuple[int, int, int] | None = None
    """Several nodes: ``(node, episode, step)`` at which that node's process is killed (its robot then
    stops, the safe action; the other nodes go on)."""
    coverage_profile: str | None = None
    """The C node's ``LLVM_PROFILE_FILE`` (a node built for coverage writes its raw profile there when it
    exits); None: the environment's."""
    compare: bool = True
    """Compare the node's actions with the reference when the episodes are over; False: the results keep
    the recorded steps for the caller to compare (:func:`embedrl.hil.compare.fill`), as the host does for
    a session in a guest (which then never loads the ONNX runtime)."""


def _session_policy(cfg: SessionConfig) -> Callable[[np.ndarray], np.ndarray]:
    """The batch policy the node must reproduce: the export's reference for its precision, or the ONNX."""
    return compare.reference(cfg.export_dir, cfg.onnx)


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

    def __init__(self, cfg: SessionConfig, interface: Interface, link: Link, node: PolicyNode) -> None:
        self.cfg, self.interface, self.link, self.node = cfg, interface, link, node
        self.step = 0
        """Global step counter: the ``Step`` signal (mod 4096)."""
        self.episode = -1
        self.in_episode = 0
        self.next_tick = 0.0
        self.schedule = {(s.episode, s.step): s for s in parse_schedule(list(cfg.inject))}
        self.injections: list[dict[str, Any]] = []
        self.previous: list[can.Message] | None = None
        self.retry_s = min(RETRY_S, cfg.node_timeout_ms / 2000)
        self.pending: list[tuple[dict[str, Any], Callable[[], dict[str, Any]]]] = []
        """Injections still running (a flood), with the record each completes when its episode ends."""
        self.unresolved: list[tuple[dict[str, Any], Injector, dict[str, Any], Any, float]] = []
        """Injection records still waiting for the node's status after them."""
        self.sent: tuple[list[can.Message], np.ndarray, int] = ([], np.zeros(0), 0)

    def end_episode(self) -> None:
        self._resolve()
        for record, finish in self.pending:
            record.update(finish())
        self.pending = []

    def begin_episode(self) -> None:
        """A new episode: a policy with memory starts from zero state on both sides of the bus (the node on
        its EpisodeStart frame)."""
        self.episode += 1
        self.in_episode = 0
        self.link.stats.episode_starts.append(len(self.link.stats.exchanges))
        self.link.send(self.link.codec.encode_episode_start(self.step))
        if self.cfg.realtime:
            self.link.stats.step_starts.append([])

    def __call__(self, obs: np.ndarray) -> np.ndarray:
        frames, decoded = self.link.codec.encode_observation(obs, self.step)
        if self.cfg.realtime:
            self._pace()
        self.node.advance(self.interface.sample_time_s)  # a sample time passed since the last step
        start = time.monotonic_ns()  # one clock read per side of a step: under UML each is a system call
        scheduled = self.schedule.get((self.episode, self.in_episode))
        if scheduled is None:
            self.link.send(frames)
            action = self._answer(obs, start)
        else:
            action = self._inject(scheduled, frames, obs)
        return self._accept(action, decoded, frames, start)

    def send(self, obs: np.ndarray) -> None:
        """The first half of a step in lock-step with other nodes: the observation goes out."""
        frames, decoded = self.link.codec.encode_observation(obs, self.step)
        self.node.advance(self.interface.sample_time_s)
        self.sent = (frames, decoded, time.monotonic_ns())
        self.link.send(frames)

    def collect(self, obs: np.ndarray) -> np.ndarray:
        """The second half: the node's action for the observation :meth:`send` sent (or NodeFault)."""
        frames, decoded, start = self.sent
        return self._accept(self._answer(obs, start), decoded, frames, start)

    def _accept(
        self,
        action: Action | None,
        decoded: np.ndarray,
        frames: list[can.Message],
        start: int,
    ) -> np.ndarray:
        """Record the node's answer to this step with the observation it decoded (compared with the reference
        when the episodes are over); an unanswered step is a fault."""
        stats = self.link.stats
        if action is None:
            stats.rx_timeouts += 1
            raise NodeFault(self._silence_reason(start / 1e9))
        stats.latencies_us.append((time.monotonic_ns() - start) / 1000.0)
        stats.exchanges.append((self.step, decoded, action.action))
        self.previous = frames
        self.step += 1
        self.in_episode += 1
        return action.action

    def _answer(self, obs: np.ndarray, sent_ns: int | None = None) -> Action | None:
        """The node's action for this step (its observation sent at ``sent_ns``, ``time.monotonic_ns``;
        None: now); unanswered, the step is sent again every ``retry_s``."""
        sent = time.monotonic() if sent_ns is None else sent_ns / 1e9
        deadline = sent + self.cfg.action_timeout_s
        until = sent + self.retry_s
        now: float | None = sent
        while True:
            action = self.link.wait_action(self.step, min(until, deadline), self.node.alive, now)
            if action is not None or until >= deadline or not self.node.alive():
                return action
            now = None
            until += self.retry_s
            frames, _ = self.link.codec.encode_observation(obs, self.step)
            self.link.stats.retries += 1
            self.link.send(frames)

    def _inject(self, scheduled: Scheduled, frames: list[can.Message], obs: np.ndarray) -> Action | None:
        """Apply one scheduled fault in place of sending ``frames``; record what the node did."""
        injector = scheduled.injector
        if injector.needs_socketcan and self.cfg.bus != "socketcan":
            raise ValueError(
                f"the fault {injector.name!r} needs SocketCAN (the C node), not bus {self.cfg.bus!r}"
            )
        self._resolve()
        stats = self.link.stats
        before = (stats.last_status, stats.last_diag) if stats.last_status and stats.last_diag else None
        stats.actions_by_step.clear()  # count the answers to this step only
        context = Context(
            self.link, self.node, self.interface, self.cfg.node_timeout_ms, self.cfg.action_timeout_s,
            self.cfg.bus, self.cfg.iface, self.previous,
        )  # fmt: skip
        extra = injector.apply(context, frames, obs, self.step)  # may leave work for the episode's end
        if injector.restarts_steps:
            self.step = 0
        action = None if injector.ends_episode else self._answer(obs)
        if action is not None:
            self.link.drain(self.retry_s / 2)  # a second answer to the same step would arrive now
        # (counted before a SAFE node's periodic safe action, which repeats the last step, can come)
        answers = stats.actions_by_step.get(self.step % STEP_MODULO, 0)
        record = {
            "kind": injector.name,
            "episode": scheduled.episode,
            "step": scheduled.step,
            "injected": injector.description,
            "expected": injector.expected,
            "detects": injector.detects,
            "detected": None,
            "answered": action is not None,
            "answered_as_expected": (action is not None) == injector.answered,
            "answer_is_safe_action": None if action is None else is_safe(action.action, self.interface),
            "answers_to_the_step": answers,
            "before": _counters(before),
            "after": None,
            **extra,
        }
        self.injections.append(record)
        self.unresolved.append((record, injector, extra, before, time.monotonic()))
        self.pending += [(record, finish) for finish in context.at_episode_end]
        if injector.ends_episode:
            raise NodeFault(f"injected: {injector.name}")
        return action

    def _resolve(self) -> None:
        """Complete the injection records with the node's first status after each: taken as the next
        steps run (waiting for it here would leave the node without observations), or now."""
        for record, injector, extra, before, since in self.unresolved:
            later = [(st, dg) for t, st, dg in self.link.stats.snapshots if t >= since]
            if later:
                after: tuple[Status, Diag] | None = later[0]
            else:
                after = _next_snapshot(self.link, self.node) if self.node.alive() else None
            record["after"] = _counters(after)
            record["detected"] = _detected(injector, before, after, extra, self.node)
        self.unresolved = []

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


@contextmanager
def _nodes_on_one_bus(
    cfg: SessionConfig, interface: Interface, count: int
) -> Iterator[tuple[list[Link], list[PolicyNode], list[BusPolicy]]]:
    """``count`` nodes on one bus (node k with node k's CAN IDs), each with its own link and bus policy,
    booted; on exit the nodes get a last status in, then are stopped and the links closed. The lists stay
    readable afterwards (the links' statistics)."""
    logger = can.Logger(cfg.log) if cfg.log else None
    links: list[Link] = []
    nodes: list[PolicyNode] = []
    policies: list[BusPolicy] = []
    try:
        for k in range(count):
            codec = Codec(interface, k, cfg.fd)
            links.append(Link(open_bus(cfg, codec), codec, Stats(), cfg.iface, None, logger))
            nodes.append(_start_node(cfg, interface, k))
            policies.append(BusPolicy(cfg, interface, links[k], nodes[k]))
        for link in links:
            link.wait_status(NODE_BOOT_S)
        yield links, nodes, policies
        for link, node in zip(links, nodes, strict=True):
            _last_status(link, node)
    finally:
        for node in nodes:
            node.stop()
        for link in links:
            link.close()
        if logger is not None:
            logger.stop()


def _run_nodes(cfg: SessionConfig, interface: Interface) -> dict[str, Any]:
    """Several nodes on one bus, one robot each (the same scenario, each robot its own seeds), in
    lock-step: every step all observations go out, then every action is collected. A robot whose node
    does not answer ends its episode as a fault; the others go on."""
    envs: list[gym.Env[np.ndarray, np.ndarray]] = []
    episodes: list[dict[str, Any]] = []
    try:
        with _nodes_on_one_bus(cfg, interface, cfg.nodes) as (links, nodes, policies):
            envs += [gym.make(interface.env_id) for _ in range(cfg.nodes)]
            for index in range(cfg.episodes):
                marks = [len(link.stats.exchanges) for link in links]
                seeds = [node_seed(cfg.seed, index, k) for k in range(cfg.nodes)]
                rows = _together(policies, envs, seeds, interface.sample_time_s)
                for k, row in enumerate(rows):
                    row.update(node=k, injected=[])
                    row[compare.EXCHANGES] = compare.share(k, marks[k], links[k].stats)
                episodes += rows
                _progress(cfg, index + 1)
                if not all(node.alive() for node in nodes):
                    break  # a node is gone: later episodes could only fail the same way
    finally:
        for env in envs:
            env.close()
    return _write_nodes_results(cfg, interface, links, episodes)


def _together(
    policies: list[BusPolicy],
    envs: list[gym.Env[np.ndarray, np.ndarray]],
    seeds: list[int],
    sample_time: float,
) -> list[dict[str, Any]]:
    """One episode of every robot at once, step by step over the bus."""
    obs, totals, rows = {}, {}, {}
    for k, (env, seed) in enumerate(zip(envs, seeds, strict=True)):
        obs[k], _ = env.reset(seed=seed)
        totals[k] = 0.0
        policies[k].begin_episode()
    active = list(range(len(envs)))
    while active:
        for k in active:
            policies[k].send(obs[k])
        for k in list(active):
            policy, env = policies[k], envs[k]
            try:
                action = policy.collect(obs[k])
            except NodeFault as fault:
                steps = policy.in_episode
                rows[k] = {
                    "seed": seeds[k], "outcome": "fault", "steps": steps, "episode_return": totals[k],
                    "time_s": steps * sample_time, "collided_with": None,
                    "trajectory": list(getattr(env.unwrapped, "trajectory", [])), "fault": str(fault),
                }  # fmt: skip
                active.remove(k)
                continue
            obs[k], reward, terminated, truncated, info = env.step(action)
            totals[k] += float(reward)
            if terminated or truncated:
                result = episode_result(env, seeds[k], info, policy.in_episode, totals[k], sample_time)
                rows[k] = {**asdict(result), "fault": None}
                active.remove(k)
    return [rows[k] for k in range(len(envs))]


def _replay(policy: BusPolicy, observations: Any, index: int, seed: int, sample_time: float) -> EpisodeResult:
    """Open loop: the next :data:`OPEN_LOOP_STEPS` recorded observations over the bus, each action
    compared with the ONNX policy's (there is no plant to apply it to)."""
    for k in range(OPEN_LOOP_STEPS):
        policy(observations[(index * OPEN_LOOP_STEPS + k) % len(observations)])
    return EpisodeResult(seed, "open-loop", OPEN_LOOP_STEPS, 0.0, OPEN_LOOP_STEPS * sample_time, None, [])


def _next_snapshot(link: Link, node: PolicyNode) -> tuple[Status, Diag] | None:
    """The node's next NodeStatus and NodeDiag (None if they do not come within :data:`SNAPSHOT_S`); a node
    on the simulation's clock sends them once a status period of that time has passed."""
    node.advance(STATUS_PERIOD_S)
    return link.snapshot(SNAPSHOT_S)


def _last_status(link: Link, node: PolicyNode) -> None:
    """Take the node's status once more before the session ends (its final counters)."""
    node.advance(STATUS_PERIOD_S)
    link.wait_status(LAST_STATUS_S)


def _counters(snapshot: tuple[Status, Diag] | None) -> dict[str, Any] | None:
    return None if snapshot is None else {**asdict(snapshot[0]), **asdict(snapshot[1])}


def _detected(
    injector: Injector,
    before: tuple[Status, Diag] | None,
    after: tuple[Status, Diag] | None,
    extra: dict[str, Any],
    node: PolicyNode,
) -> bool | None:
    """Whether the node registered the fault: the counter(s) the class must move grew (any of them)."""
    if injector.detects is None:
        return None  # a class to tolerate, not to detect
    if injector.detects == "node_exit":
        return bool(extra.get("node_died", not node.alive()))
    old, new = _counters(before), _counters(after)
    if old is None or new is None:
        return False
    if injector.detects == "bus_state":
        return bool(new["bus_state"] == "BUS_OFF")
    return any(new[key] > old[key] for key in injector.detects.split("|"))


def node_seed(seed: int, episode: int, node_id: int) -> int:
    """The seed of robot ``node_id``'s episode ``episode`` (:data:`NODE_SEED_STRIDE`)."""
    return seed + episode + node_id * NODE_SEED_STRIDE


def _start_node(cfg: SessionConfig, interface: Interface, node_id: int = 0) -> PolicyNode:
    return NODE_KINDS[cfg.node].start(cfg, interface, node_id, lambda: _session_policy(cfg))


def open_bus(cfg: SessionConfig, codec: Codec) -> can.BusABC:
    """The simulator's socket for one node: only that node's IDs pass (in the kernel on SocketCAN)."""
    return can.Bus(
        interface=cfg.bus, channel=cfg.iface, receive_own_messages=False, fd=cfg.fd,
        can_filters=[{"can_id": i, "can_mask": 0x7FF, "extended": False} for i in codec.receive_ids],
    )  # fmt: skip


def _run_robots(cfg: SessionConfig, interface: Interface) -> dict[str, Any]:
    """A scenario with several robots: one node per robot on one bus, every robot in one episode, in
    lock-step.

    Every step each robot's observation goes to its own node, then every action is collected and the
    scenario's team env (:func:`~embedrl.train.scenarios.team_env`) steps. A robot whose node does not
    answer is in the fault path: it stops (the safe action) and its row ends as a fault, while the other
    robots' nodes keep driving theirs. One row per robot and episode (``node`` = robot index, ``seed`` =
    the episode's seed)."""
    from embedrl.train.scenarios import BY_ENV_ID, team_env

    episodes: list[dict[str, Any]] = []
    env = team_env(BY_ENV_ID[interface.env_id])
    agents = list(env.possible_agents)
    safe = np.asarray(interface.safe_action, dtype=np.float32)
    try:
        with _nodes_on_one_bus(cfg, interface, len(agents)) as (links, nodes, policies):
            for index in range(cfg.episodes):
                seed = cfg.seed + index
                marks = [len(link.stats.exchanges) for link in links]
                obs, _ = env.reset(seed=seed)
                totals = [0.0] * len(agents)
                faults: list[str | None] = [None] * len(agents)
                for policy in policies:
                    policy.begin_episode()
                while env.agents:
                    live = [k for k, a in enumerate(agents) if a in env.agents and faults[k] is None]
                    for k in live:
                        if cfg.kill_node == (k, index, policies[k].in_episode):
                            nodes[k].stop()
                        policies[k].send(obs[agents[k]])
                    actions = {a: safe for a in env.agents}
                    for k in live:
                        try:
                            actions[agents[k]] = policies[k].collect(obs[agents[k]])
                        except NodeFault as fault:
                            faults[k] = str(fault)
                    stepped, rewards, _, _, _ = env.step(actions)
                    obs.update(stepped)
                    for agent, r in rewards.items():
                        totals[agents.index(agent)] += float(r)
                for k in range(len(agents)):
                    steps = len(env.trajectories[k]) - 1
                    hit = env._world.hits[k] if env._world is not None else None
                    killed = cfg.kill_node is not None and cfg.kill_node[:2] == (k, index)
                    episodes.append({
                        "seed": seed, "outcome": "fault" if faults[k] else env.outcomes[k], "steps": steps,
                        "episode_return": totals[k], "time_s": steps * interface.sample_time_s,
                        "collided_with": hit, "trajectory": list(env.trajectories[k]), "fault": faults[k],
                        "node": k, "injected": ["kill"] if killed else [],
                        compare.EXCHANGES: compare.share(k, marks[k], links[k].stats),
                        "robots": list(env.outcomes),
                    })  # fmt: skip
                _progress(cfg, index + 1)
                if not all(node.alive() for node in nodes):
                    break  # a node is gone: its robot could only fault in later episodes
    finally:
        env.close()
    return _write_nodes_results(cfg, interface, links, episodes)


def _write_nodes_results(
    cfg: SessionConfig, interface: Interface, links: list[Link], episodes: list[dict[str, Any]]
) -> dict[str, Any]:
    """Several nodes' results: merged statistics, every node's last status and diagnostics."""
    stats = Stats.merged([link.stats for link in links])
    results = _results(cfg, stats, episodes, [], interface.sample_time_s)
    results[compare.EXCHANGES] = {str(k): compare.recorded(link.stats) for k, link in enumerate(links)}
    results["nodes"] = [
        {
            "node_id": k,
            "status": asdict(link.stats.last_status) if link.stats.last_status else None,
            "diag": asdict(link.stats.last_diag) if link.stats.last_diag else None,
        }
        for k, link in enumerate(links)
    ]
    results["crc_errors"] = sum(int(n["status"]["crc_errors"]) for n in results["nodes"] if n["status"])
    results["sequence_errors"] = sum(
        int(n["status"]["sequence_errors"]) for n in results["nodes"] if n["status"]
    )
    _compared(cfg, results, interface)
    Path(cfg.results).write_text(json.dumps(results, indent=2) + "\n")
    return results


def _compared(cfg: SessionConfig, results: dict[str, Any], interface: Interface) -> None:
    """The node's actions compared with the reference now (``cfg.compare``), else left to the caller."""
    if cfg.compare:
        compare.fill(results, interface, lambda: _session_policy(cfg))


def _progress(cfg: SessionConfig, done: int) -> None:
    """Episodes done so far, for whoever watches ``cfg.progress`` (replaced whole: never half-written)."""
    if cfg.progress is not None:
        path = Path(cfg.progress)
        path.with_suffix(".tmp").write_text(f"{done} {cfg.episodes}\n")
        path.with_suffix(".tmp").replace(path)


def run(cfg: SessionConfig, interface: Interface | None = None) -> dict[str, Any]:
    """Run the episodes; return the results (also written to cfg.results). ``interface``: the one in
    ``cfg.interface``, already read by the caller in this process (a session in a guest reads it)."""
    if interface is None:
        interface = load_interface(Path(cfg.interface))
    if interface.robots > 1:
        return _run_robots(cfg, interface)
    if cfg.nodes > 1:
        return _run_nodes(cfg, interface)
    stats = Stats()
    open_loop = interface.env_id == NO_ENV
    replayed = np.load(cfg.observations, allow_pickle=False) if open_loop and cfg.observations else None
    if open_loop and replayed is None:
        raise ValueError("a policy without an env runs in open loop: give its observations")
    episodes: list[dict[str, Any]] = []
    with ExitStack() as cleanup:  # whatever was started is stopped, even when interrupted while starting
        codec = Codec(interface, fd=cfg.fd)
        bus = open_bus(cfg, codec)
        cleanup.callback(bus.shutdown)  # at once: an interrupt may land before the link owns it
        link = Link(bus, codec, stats, cfg.iface, cfg.log)
        cleanup.callback(link.close)
        node = _start_node(cfg, interface)
        cleanup.callback(node.stop)
        policy = BusPolicy(cfg, interface, link, node)
        cleanup.callback(policy.end_episode)  # nothing of an injection keeps running
        env = None if open_loop else _Tally(gym.make(interface.env_id))
        if env is not None:
            cleanup.callback(env.close)
        link.wait_status(NODE_BOOT_S)
        first_diff = 0
        loop_start = time.perf_counter()
        for index in range(cfg.episodes):
            seed = cfg.seed + index
            policy.begin_episode()
            try:
                if env is None:
                    result = _replay(policy, replayed, index, seed, interface.sample_time_s)
                else:
                    result = run_episode(env, policy, seed, interface.sample_time_s)
                policy.end_episode()
                row: dict[str, Any] = {**asdict(result), "fault": None}
            except NodeFault as fault:
                policy.end_episode()
                row = {
                    "seed": seed,
                    "outcome": "fault",
                    "steps": policy.in_episode,
                    "episode_return": env.total if env else 0.0,
                    "time_s": policy.in_episode * interface.sample_time_s,
                    "collided_with": None,
                    "trajectory": list(getattr(env.unwrapped, "trajectory", [])) if env else [],
                    "fault": str(fault),
                }
            row["injected"] = [r["kind"] for r in policy.injections if r["episode"] == index]
            row[compare.EXCHANGES] = compare.share(0, first_diff, stats)
            first_diff = len(stats.exchanges)
            episodes.append(row)
            _progress(cfg, index + 1)
            if row["fault"] and not node.alive():
                break  # the node is gone: later episodes could only fail the same way
        loop_seconds = time.perf_counter() - loop_start
        _last_status(link, node)
    results = _results(cfg, stats, episodes, policy.injections, interface.sample_time_s)
    results["loop_seconds"] = loop_seconds  # the episodes' wall-clock time, start-up and wind-down left out
    if isinstance(node, FirmwareNode):
        results["firmware"] = {
            "machine": cfg.qemu_machine,
            "starts": node.starts,
            "instructions_per_step": instruction_summary(node.step_instructions(), node.tick_instructions),
            "step_instructions": node.step_instructions(),
            "stack_peak_bytes": node.stack_peak(),
        }
    results[compare.EXCHANGES] = {"0": compare.recorded(stats)}
    _compared(cfg, results, interface)
    Path(cfg.results).write_text(json.dumps(results, indent=2) + "\n")
    return results


def _results(
    cfg: SessionConfig,
    stats: Stats,
    episodes: list[dict[str, Any]],
    injections: list[dict[str, Any]],
    sample_time: float,
) -> dict[str, Any]:
    lat = np.array(stats.latencies_us) if stats.latencies_us else np.zeros(1)
    status = stats.last_status
    return {
        "episodes": episodes,
        "steps": int(sum(e["steps"] for e in episodes)),
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
        "node_diag": asdict(stats.last_diag) if stats.last_diag else None,
        "retries": stats.retries,
        "injections": injections,
        "fault_catalogue": catalogue_summary(injections),
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


def catalogue_summary(injections: list[dict[str, Any]]) -> dict[str, dict[str, int | None]]:
    """Per fault class: how many were injected, detected by the node (None for the classes it must only
    tolerate), answered as the class requires."""
    summary: dict[str, dict[str, int | None]] = {}
    for r in injections:
        detectable = r["detects"] is not None
        row = summary.setdefault(
            r["kind"], {"injected": 0, "detected": 0 if detectable else None, "answered_as_expected": 0}
        )
        row["injected"] = int(row["injected"] or 0) + 1
        if detectable:
            row["detected"] = int(row["detected"] or 0) + bool(r["detected"])
        row["answered_as_expected"] = int(row["answered_as_expected"] or 0) + r["answered_as_expected"]
    return summary


def link_errors(status: Status | None, key: str) -> int | None:
    """Errors the node counted (from its last status frame)."""
    return None if status is None else int(getattr(status, key))


if __name__ == "__main__":
    fields = json.loads(Path(sys.argv[1]).read_text())
    kill = fields.get("kill_node")
    config = SessionConfig(
        **{**fields, "inject": tuple(fields.get("inject", ())), "kill_node": tuple(kill) if kill else None}
    )
    run(config)
