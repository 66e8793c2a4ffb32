"""The deck's walking robot over CAN: a small walker policy (SB3 TD3 actor 17-32-32-6, untrained, seeded)
exported for the walker scenario, 17 observations in 9 frames and 6 actions in 3 frames a step, in lock-step
equal to the MuJoCo simulation; on the Python node over python-can's virtual bus (fast), on the C node
over vcan and on the Cortex-M4F firmware node (slow); the run's walk drawn again from its positions."""

from __future__ import annotations

import json
from pathlib import Path
from typing import Any

import gymnasium as gym
import pytest
import torch
from stable_baselines3 import TD3

from embedrl.cli import main
from embedrl.export.contract.layout import layout
from embedrl.hil.sandbox import Guest
from embedrl.train.scenarios import WALKER
from embedrl.train.walker_env import (
    WALK_FRAME_PX,
    WALK_FRAME_STRIDE,
    render_joint_trajectory,
    walk_frame_steps,
)
from tests.hil.helpers import hil

OBSERVATION_FRAMES = 9
"""17 observations, two 20-bit values per classic CAN frame."""


@pytest.fixture(scope="module")
def walker_export(tmp_path_factory: pytest.TempPathFactory) -> Path:
    work = tmp_path_factory.mktemp("walker")
    torch.manual_seed(0)
    model = TD3(
        "MlpPolicy", gym.make(WALKER.env_id), seed=0, device="cpu", policy_kwargs={"net_arch": [32, 32]}
    )
    model.save(work / "walker.zip")
    out = work / "export"
    assert (
        main(
            ["export", str(work / "walker.zip"), "--scenario", "walker", "--out", str(out), "--episodes", "0"]
        )
        == 0
    )
    return out


def _check_lock_step(report: dict[str, Any], episodes: int) -> None:
    assert len(layout(WALKER).observation) == OBSERVATION_FRAMES
    assert report["episodes"] == episodes and report["faults"] == 0 and report["steps"] > episodes
    assert report["outcomes_differing_from_simulation"] == []
    assert report["max_action_abs_diff"] <= 1e-5
    for row in report["per_episode"]:  # the same walk: returns equal to a millionth or so
        assert row["episode_return"] == pytest.approx(row["simulation_return"], rel=1e-5)
    assert report["frames_tx"] == OBSERVATION_FRAMES * (report["steps"] + report["retries"])
    assert report["verdict"]["passed"], report["verdict"]


def test_the_walker_export_carries_the_walker_interface(walker_export: Path) -> None:
    interface = json.loads((walker_export / "interface.json").read_text())
    assert interface["env_id"] == WALKER.env_id and interface["sample_time_s"] == WALKER.sample_time_s
    assert [f["name"] for f in interface["observation"]] == [f.name for f in WALKER.observation]
    assert [f["name"] for f in interface["action"]] == [f.name for f in WALKER.action]
    header = (walker_export / "c" / "policy.h").read_text()
    assert "#define POLICY_OBS_DIM 17u" in header
    assert "#define POLICY_ACT_THIGH_TORQUE 0u" in header


def test_a_walker_policy_in_lock_step_on_the_python_node(walker_export: Path, tmp_path: Path) -> None:
    _check_lock_step(hil(None, walker_export, tmp_path, "--node", "python", "--episodes", "3"), 3)


@pytest.mark.slow
def test_a_walker_policy_in_lock_step_on_the_c_node_over_vcan(
    guest: Guest, walker_export: Path, tmp_path: Path
) -> None:
    _check_lock_step(hil(guest, walker_export, tmp_path, "--episodes", "3"), 3)


@pytest.mark.qemu
@pytest.mark.slow
def test_a_walker_policy_in_lock_step_on_the_firmware_node(
    guest: Guest, walker_export: Path, tmp_path: Path
) -> None:
    report = hil(
        guest, walker_export, tmp_path, "--node", "firmware", "--target", "cortex-m4", "--episodes", "1"
    )
    _check_lock_step(report, 1)
    per_step = report["instructions_per_step"]
    assert report["node"] == "firmware" and per_step["steps"] == report["steps"]
    # a 17-32-32-6 actor: about 1,900 multiply-adds, a few thousand instructions with the frames' codec
    assert 3_000 < per_step["mean"] < 30_000 and per_step["max"] < 2 * per_step["mean"]
    assert 0 < report["time_on_target"]["fraction_of_sample_time"] < 0.05


def test_the_hil_walk_is_an_animation_of_the_runs_episodes(walker_export: Path, tmp_path: Path) -> None:
    from PIL import Image

    plots = tmp_path / "plots"
    report = hil(None, walker_export, tmp_path, "--node", "python", "--episodes", "2", "--plot", str(plots))
    steps = [row["steps"] for row in report["per_episode"]]
    assert sum(steps) == report["steps"] and all(row["distance"] is not None for row in report["per_episode"])
    with Image.open(plots / "hil_walk.gif") as gif:
        assert getattr(gif, "is_animated", False) and gif.size == (WALK_FRAME_PX, WALK_FRAME_PX)
        assert getattr(gif, "n_frames", 1) == sum(
            len(walk_frame_steps(n)) for n in steps
        )  # every episode, start to end
        assert gif.info["duration"] == pytest.approx(WALK_FRAME_STRIDE * 1000 * WALKER.sample_time_s, abs=5)
    with Image.open(plots / "hil_walk.png") as strip:  # the first episode
        assert strip.size[1] == WALK_FRAME_PX and strip.size[0] >= 2 * WALK_FRAME_PX


def test_a_walk_replays_the_recorded_positions() -> None:
    import numpy as np

    env = gym.make(WALKER.env_id)
    env.reset(seed=4)
    for _ in range(9):
        env.step(np.full(6, 0.5, dtype=np.float32))
    rows = env.unwrapped.joint_trajectory  # type: ignore[attr-defined]
    assert len(rows) == 10 and len(rows[0]) == 9  # after reset and after each of the 9 steps
    assert walk_frame_steps(9) == [0, 8, 9]
    frames = render_joint_trajectory(rows)
    assert len(frames) == 3 and frames[0].shape == (WALK_FRAME_PX, WALK_FRAME_PX, 3)
    assert not np.array_equal(frames[0], frames[-1])  # the body moved between the first and the last
    again = render_joint_trajectory([rows[0], rows[1]])
    assert np.array_equal(again[0], frames[0])  # the same positions, the same picture
    with pytest.raises(ValueError, match="step 1 of the walk is not 9 finite positions"):
        render_joint_trajectory([rows[0], (*rows[1][:8], float("nan"))])
