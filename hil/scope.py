"""``embedrl scope``: one episode as a control engineer reads a controller: every observation field and
action against time, held for one sample period as the node holds them, grouped by unit, and what the CAN
signals make of the observation (the node decodes each field at its signal's resolution)."""

from __future__ import annotations

from pathlib import Path
from typing import Any

import numpy as np

from embedrl.common import atomic_write
from embedrl.export.contract.layout import rounding_errors
from embedrl.hil.codec import Codec

EXACT = 1e-12
"""Where a field the CAN signal carries exactly is drawn on the log axis."""


def record(policy: Any, scenario: str, seed: int, extra: dict[str, Any]) -> dict[str, Any]:
    """One seeded episode: observations (and as decoded from their CAN frames), actions, time, outcome."""
    import gymnasium as gym

    from embedrl.train.scenarios import SCENARIOS

    interface = SCENARIOS[scenario]
    codec = Codec(interface)
    env = gym.make(interface.env_id, **extra)
    obs, info = env.reset(seed=seed)
    observations: list[np.ndarray] = []
    decoded: list[np.ndarray] = []
    actions: list[np.ndarray] = []
    while True:
        action = np.asarray(policy(obs), dtype=np.float32)
        observations.append(np.asarray(obs, dtype=np.float32))
        decoded.append(codec.encode_observation(obs, len(actions))[1])
        actions.append(action)
        obs, _, terminated, truncated, info = env.step(action)
        if terminated or truncated:
            break
    env.close()
    outcome = "success" if info["is_success"] else "collision" if info["collided"] else "timeout"
    return {
        "interface": interface, "observations": np.array(observations), "decoded": np.array(decoded),
        "actions": np.array(actions), "outcome": outcome, "seed": seed,
    }  # fmt: skip


def plot(episode: dict[str, Any], path: Path, title: str) -> None:
    """One panel per unit of the observation fields, one for the actions, one for the CAN signals'
    rounding; time in seconds with every sample marked."""
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    interface = episode["interface"]
    dt = interface.sample_time_s
    steps = len(episode["actions"])
    t = np.arange(steps) * dt
    edges = np.arange(steps + 1) * dt  # each value held for its sample period
    groups: dict[str, list[int]] = {}
    for index, f in enumerate(interface.observation):
        groups.setdefault(f.unit or "-", []).append(index)
    panels = len(groups) + 2
    fig, axes = plt.subplots(panels, 1, figsize=(10, 1.9 * panels + 0.6), sharex=True)
    for ax, (unit, indices) in zip(axes, groups.items(), strict=False):
        for i in indices:
            ax.stairs(
                episode["observations"][:, i],
                edges,
                baseline=None,
                label=interface.observation[i].name,
                lw=1.5,
            )
        ax.set_ylabel(f"observation\n[{unit}]")
        ax.legend(loc="center left", bbox_to_anchor=(1.01, 0.5), fontsize="small")
    act = axes[len(groups)]
    for j, f in enumerate(interface.action):
        act.stairs(episode["actions"][:, j], edges, baseline=None, label=f.name, lw=1.5)
    act.set_ylabel("action\n(held one sample)")
    act.legend(loc="center left", bbox_to_anchor=(1.01, 0.5), fontsize="small")
    can = axes[-1]
    error = np.abs(episode["decoded"].astype(np.float64) - episode["observations"])
    for i, f in enumerate(interface.observation):
        can.stairs(np.maximum(error[:, i], EXACT), edges, baseline=None, label=f.name, lw=0.8)
    worst = rounding_errors(interface)["observation"]
    can.axhline(worst, color="k", ls="--", lw=0.8, label=f"largest rounding (half a step) {worst:.1e}")
    can.set(yscale="log", ylabel=f"|field - CAN signal|\nas the node decodes it\n({EXACT:g}: exact)")
    can.legend(loc="center left", bbox_to_anchor=(1.01, 0.5), fontsize="x-small", ncols=2)
    can.set_xlabel(f"time [s] (sample time {dt} s: one mark per step)")
    can.set_xticks(t, minor=True)
    fig.suptitle(f"{title}: seed {episode['seed']}, {steps} steps, {episode['outcome']}")
    fig.tight_layout()
    try:
        atomic_write(path, lambda tmp: fig.savefig(tmp, dpi=100, bbox_inches="tight", format="png"))
    finally:
        plt.close(fig)
