"""A HIL run's report: the evaluation format plus the HIL keys, beside the simulation of the same seeds.

The simulation drives the export's own precision (float32 ONNX, or the bit-exact int8/q15 model) with the
node's rule (an action the node would refuse is the safe action), so an episode that ends differently
ended so because of the bus, the node or the C, not because of the policy.
"""

from __future__ import annotations

from pathlib import Path
from typing import TYPE_CHECKING, Any

import numpy as np

from embedrl.common import owned_temporary_folder
from embedrl.export.contract.layout import rounding_errors
from embedrl.train.evaluate import REPORT_KEYS, EpisodeResult, EvalReport, evaluate
from embedrl.train.interface import NO_ENV, Interface

if TYPE_CHECKING:
    from collections.abc import Callable

    from embedrl.hil.options import RunOptions

SIMULATION = "simulation (onnxruntime)"
COPIED_KEYS = (
    "steps", "max_action_abs_diff", "first_divergent_step", "frames_tx", "frames_rx", "crc_errors",
    "sequence_errors", "rx_timeouts", "sandbox", "sandbox_detail", "latency_us", "deadline_misses",
    "jitter_us", "node_status", "node_diag", "retries", "injections", "fault_catalogue", "nodes", "firmware",
    "node_binary_sha256", "action_diffs", "coverage",
)  # fmt: skip
"""The session's results that the report carries as they are."""


def robot_outcome(outcome: str) -> str:
    """A robot's outcome in the report's terms: ``stopped`` (the other robot crashed) counts as a timeout."""
    return "timeout" if outcome == "stopped" else outcome


def hil_report(options: RunOptions, interface: Interface, results: dict[str, Any]) -> dict[str, Any]:
    """The report of a session's ``results``, the simulation on the same seeds, the plots asked for."""
    from embedrl.export.reference import precision_of

    episodes = [
        EpisodeResult(
            e["seed"], robot_outcome(e["outcome"]), e["steps"], e["episode_return"], e["time_s"],
            e.get("collided_with"), [tuple(p) for p in e["trajectory"]], distance=e.get("distance"),
            joint_trajectory=[tuple(q) for q in e.get("joint_trajectory", [])],
        )
        for e in results["episodes"]
    ]  # fmt: skip
    report = EvalReport.from_results(episodes, options.seed, f"HIL {options.export_dir}")
    sim, pairs = _simulation(options, interface, results, episodes)
    sim_results = sim.results if sim else [None] * len(episodes)
    differing = [h.seed for h, s in zip(episodes, sim_results, strict=True) if s and h.outcome != s.outcome]
    extra = {k: results.get(k) for k in COPIED_KEYS}
    extra["faults"] = sum(e.outcome == "fault" for e in episodes)
    extra["simulation"] = {k: getattr(sim, k) for k in REPORT_KEYS} if sim else None
    extra["outcomes_differing_from_simulation"] = differing
    extra["max_return_abs_diff"] = (
        max(abs(h.episode_return - s.episode_return) for h, s in zip(episodes, sim.results, strict=True))
        if sim
        else None
    )
    extra["open_loop"] = sim is None
    extra["precision"] = precision_of(options.export_dir)  # what the node's actions were compared with
    extra["two_robots"] = pairs
    extra["can_rounding_error"] = rounding_errors(interface)  # the signals' resolution, stated
    extra["node"] = options.node
    extra["sample_time_s"] = interface.sample_time_s  # the round trip's yardstick in the summary
    firmware = results.get("firmware")
    extra["target"] = options.firmware_target if firmware else None
    extra["instructions_per_step"] = firmware["instructions_per_step"] if firmware else None
    extra["time_on_target"] = (
        _time_on_target(options, firmware["instructions_per_step"], interface.sample_time_s)
        if firmware and firmware["instructions_per_step"]
        else None
    )
    data = report.to_json(extra)
    for row, e, s in zip(data["per_episode"], results["episodes"], sim_results, strict=True):
        row["fault"] = e["fault"]
        row["simulation_return"] = s.episode_return if s else None  # lock-step: equal up to quantisation
        row["injected"] = e["injected"]
        row["max_action_abs_diff"] = e["max_action_abs_diff"]
        row["node"] = e.get("node", 0)
    data["per_node"] = _per_node(data["per_episode"], options.nodes, differing)
    if options.plot:
        _plot(options, interface, report, episodes, results, sim)
    return data


def _simulated_policy(options: RunOptions, interface: Interface) -> Callable[[np.ndarray], np.ndarray]:
    """The export's policy in the simulation, with the node's rule: an action it would refuse is the safe
    action."""
    from embedrl.export.reference import reference_policy
    from embedrl.hil.nodes import action_ok
    from embedrl.train.evaluate import start_episode

    reference = reference_policy(options.export_dir)  # the export's precision: float, int8, q15
    safe = np.asarray(interface.safe_action, dtype=np.float32)

    class Simulated:
        def __call__(self, obs: np.ndarray) -> np.ndarray:
            out = reference(obs.reshape(1, -1)).reshape(-1)
            return out if action_ok(out, interface) else safe

        def reset(self) -> None:  # a policy with memory: each episode from zero state, as on the node
            start_episode(reference)

    return Simulated()


def _simulation(
    options: RunOptions, interface: Interface, results: dict[str, Any], episodes: list[EpisodeResult]
) -> tuple[EvalReport | None, dict[str, int] | None]:
    """The simulation's report, one row per HIL row (None in open loop: no plant to simulate; the actions
    are compared per step), and for a scenario with several robots the count of episodes every robot got
    through."""
    if interface.env_id == NO_ENV:
        return None, None
    simulated = _simulated_policy(options, interface)
    if interface.robots > 1:
        return _team_simulation(options, interface, results, episodes, simulated)
    from embedrl.hil.session import NODE_SEED_STRIDE

    # each node's robot on its own seeds (node_seed), in the order the HIL rows have
    per_episode = -(-len(episodes) // options.nodes)
    by_seed = {
        r.seed: r
        for k in range(options.nodes)
        for r in evaluate(
            simulated, per_episode, options.seed + k * NODE_SEED_STRIDE, SIMULATION, False,
            interface.env_id, interface.sample_time_s,
        ).results
    }  # fmt: skip
    return EvalReport.from_results([by_seed[h.seed] for h in episodes], options.seed, SIMULATION), None


def _team_simulation(
    options: RunOptions,
    interface: Interface,
    results: dict[str, Any],
    episodes: list[EpisodeResult],
    simulated: Callable[[np.ndarray], np.ndarray],
) -> tuple[EvalReport, dict[str, int]]:
    """One row per robot; the simulation drives every robot of the episode."""
    pairs = evaluate(simulated, options.episodes, options.seed, SIMULATION, False, interface.env_id).results
    by_seed = {r.seed: r for r in pairs}
    robot_rows = [
        EpisodeResult(
            h.seed, robot_outcome(by_seed[h.seed].robots[k]), h.steps, by_seed[h.seed].robot_returns[k],
            h.time_s, None,
        )
        for h, k in zip(episodes, (e["node"] for e in results["episodes"]), strict=True)
    ]  # fmt: skip
    hil_pairs: dict[int, list[str]] = {}
    for e in results["episodes"]:
        hil_pairs.setdefault(e["seed"], []).append(e["outcome"])
    counts = {
        "episodes": len(hil_pairs),
        "hil_both_through": sum(
            len(o) == interface.robots and all(x == "success" for x in o) for o in hil_pairs.values()
        ),
        "simulation_both_through": sum(r.outcome == "success" for r in pairs),
    }
    return EvalReport.from_results(robot_rows, options.seed, SIMULATION), counts


def _time_on_target(options: RunOptions, per_step: dict[str, Any], sample_time_s: float) -> dict[str, Any]:
    """The node cycle's worst step at the modelled part's clock, with the cycles per instruction of the
    export's traced inference (:func:`embedrl.export.target.cycles_per_instruction`), and the margin to the
    sample time."""

    from embedrl.export import cycles, target

    with owned_temporary_folder("embedrl-cycles-") as tmp:
        traced = target.cycles_per_instruction(options.export_dir, options.firmware_target, Path(tmp))
    timed = cycles.time_on_target(per_step["max"], traced, options.firmware_target, sample_time_s)
    step_s = timed["estimated_inference_us"] / 1e6
    return {
        "worst_step_instructions": per_step["max"],
        "estimated_cycles": timed["estimated_cycles_per_inference"],
        "cycles_per_instruction": round(traced["cycles_per_instruction"], 3),
        "clock": timed["clock"],
        "estimated_step_us": timed["estimated_inference_us"],
        "sample_time_s": sample_time_s,
        "margin_s": round(sample_time_s - step_s, 6),
        "fraction_of_sample_time": timed["fraction_of_sample_time"],
    }


def _per_node(rows: list[dict[str, Any]], nodes: int, differing: list[int]) -> dict[int, dict[str, Any]]:
    return {
        k: {
            "episodes": sum(r["node"] == k for r in rows),
            "successes": sum(r["node"] == k and r["outcome"] == "success" for r in rows),
            "faults": sum(r["node"] == k and r["outcome"] == "fault" for r in rows),
            "differing_from_simulation": [
                r["seed"] for r in rows if r["node"] == k and r["seed"] in differing
            ],
        }
        for k in range(nodes)
    }


def _plot(
    options: RunOptions, interface: Interface, report: EvalReport, episodes: list[EpisodeResult],
    results: dict[str, Any], sim: EvalReport | None,
) -> None:  # fmt: skip
    from embedrl.hil.plots import plot_action_differences, plot_latency
    from embedrl.train.plots import plot_trajectories

    assert options.plot is not None
    if any(e.trajectory for e in episodes):  # envs with a map (the warehouse scenarios)
        nodes = [e.get("node", 0) for e in results["episodes"]]
        plot_trajectories(report, options.plot / "hil_trajectories.png", overlay=sim, nodes=nodes)
    plot_latency(
        results["latencies_us"], options.plot / "hil_latency.png", results["sandbox"], options.realtime,
        interface.sample_time_s, results["config"]["node_timeout_ms"],  # the watchdog this run's node had
    )  # fmt: skip
    plot_action_differences(
        results["action_diffs"],
        options.plot / "hil_action_diff.png",
        rounding_errors(interface)["action"],
    )
    if any(e.joint_trajectory for e in episodes):  # the walker: its walk drawn again from the run's positions
        save_walk(episodes, options.plot, interface.sample_time_s)


WALK_FILES = ("hil_walk.gif", "hil_walk.png")
"""A walker run's walk: every episode one after the other as an animation, and a strip of the first."""


def save_walk(episodes: list[EpisodeResult], folder: Path, sample_time_s: float) -> None:
    """Every episode's recorded positions drawn again by MuJoCo's renderer into :data:`WALK_FILES`, each
    frame captioned with its episode, seed and time (faulted episodes, without positions, are left out)."""
    from embedrl.train.rendering import save_episode
    from embedrl.train.walker_env import WALK_FRAME_STRIDE, render_joint_trajectory, walk_frame_steps

    frames: list[np.ndarray] = []
    captions: list[str] = []
    first = 0
    for number, e in enumerate(episodes, start=1):
        if not e.joint_trajectory:
            continue
        shown = render_joint_trajectory(e.joint_trajectory)
        if not frames:
            first = len(shown)
        frames += shown
        steps = walk_frame_steps(len(e.joint_trajectory) - 1)
        captions += [f"HIL episode {number}, seed {e.seed}: t = {k * sample_time_s:.2f} s" for k in steps]
    gif, strip = (folder / name for name in WALK_FILES)
    save_episode(frames, gif, WALK_FRAME_STRIDE * sample_time_s, captions)
    save_episode(frames[:first], strip, sample_time_s, captions[:first])
