"""The node's actions against the policy it must reproduce, compared once the session's episodes are over.

The session records every answered step (:attr:`embedrl.hil.link.Stats.exchanges`: its Step counter, the
observation the node decoded, the node's action) and where each episode began; :func:`fill` then runs the
export's reference for its precision (:func:`reference`) on those observations in the order the node saw
them, a policy with memory started again from zero state at each episode as the node is, and writes the
differences into the results: per step and node (``action_diffs``), per episode and in all
(``max_action_abs_diff``), and the first step whose action is off by more than :data:`TOLERANCE`
(``first_divergent_step``). An action the node would refuse (non-finite or out of range) is compared with
the safe action, which a correct node sends instead.

Nothing of it needs the bus: a session in a slow (emulated) guest leaves the comparison to the host
(:attr:`embedrl.hil.session.SessionConfig.compare` false), so the guest never loads the ONNX runtime.
"""

from __future__ import annotations

from collections.abc import Callable
from pathlib import Path
from typing import TYPE_CHECKING, Any

import numpy as np

from embedrl.hil.nodes import action_ok
from embedrl.train.evaluate import start_episode

if TYPE_CHECKING:
    from embedrl.hil.link import Stats
    from embedrl.train.interface import Interface

TOLERANCE = 1e-5
"""The largest difference between the node's action and the reference's that still counts as equal."""
EXCHANGES = "exchanges"
"""The results' key of the recorded steps (per node) and of each episode's share of them, until compared."""

Policy = Callable[[np.ndarray], np.ndarray]


def reference(export_dir: str | None, onnx: str) -> Policy:
    """The batch policy the node must reproduce: the export's reference for its precision, or (no export
    folder) the ONNX under onnxruntime."""
    from embedrl.export.reference import OnnxPolicy, reference_policy

    if export_dir is not None:
        return reference_policy(Path(export_dir))
    return OnnxPolicy(Path(onnx))


def recorded(stats: Stats) -> dict[str, list[Any]]:
    """One node's recorded steps as the results carry them (JSON: floats round-trip exactly)."""
    return {
        "steps": [step for step, _, _ in stats.exchanges],
        "observations": [observation.tolist() for _, observation, _ in stats.exchanges],
        "actions": [action.tolist() for _, _, action in stats.exchanges],
        "episode_starts": list(stats.episode_starts),
    }


def share(node: int, start: int, stats: Stats) -> list[int]:
    """An episode's share of node ``node``'s recorded steps: from ``start`` to those recorded so far."""
    return [node, start, len(stats.exchanges)]


def fill(results: dict[str, Any], interface: Interface, policy: Callable[[], Policy]) -> None:
    """Replace the recorded steps in ``results`` by their comparison with the reference (``policy()``
    makes one per node)."""
    per_node: dict[str, list[float]] = {}
    first: int | None = None
    for node, steps in results.pop(EXCHANGES).items():
        per_node[node], divergent = _compare(steps, policy(), interface)
        if divergent is not None:
            first = divergent if first is None else min(first, divergent)
    for row in results["episodes"]:
        node, start, end = row.pop(EXCHANGES)
        row["max_action_abs_diff"] = max(per_node[str(node)][start:end], default=None)
    every = [diff for diffs in per_node.values() for diff in diffs]
    results["max_action_abs_diff"] = max(every) if every else None
    results["action_diffs"] = per_node
    results["first_divergent_step"] = first


def _compare(
    steps: dict[str, list[Any]], policy: Policy, interface: Interface
) -> tuple[list[float], int | None]:
    """One node's differences, step by step, and the Step counter of its first divergent action."""
    starts = set(steps["episode_starts"])
    safe = np.asarray(interface.safe_action, dtype=np.float32)
    diffs: list[float] = []
    first: int | None = None
    rows = zip(steps["steps"], steps["observations"], steps["actions"], strict=True)
    for index, (step, observation, action) in enumerate(rows):
        if index in starts:
            start_episode(policy)
        decoded = np.asarray(observation, dtype=np.float64).astype(np.float32).reshape(1, -1)
        expected = np.asarray(policy(decoded)).reshape(-1)
        if not action_ok(expected, interface):  # what a correct node sends instead
            expected = safe
        diff = float(np.max(np.abs(np.asarray(action, dtype=np.float64) - expected)))
        diffs.append(diff if np.isfinite(diff) else float("inf"))
        if diffs[-1] > TOLERANCE and first is None:
            first = step
    return diffs, first
