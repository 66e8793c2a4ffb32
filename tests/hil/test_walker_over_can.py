"""The deck's walking robot over CAN: a small walker policy (SB3 TD3 actor 17-32-32-6, untrained, seeded)
exported for the walker scenario, 17 observations in 9 frames and 6 actions in 3 frames a step, in lock-step
equal to the MuJoCo simulation; on the Python node over python-can's virtual bus (fast) and on the C node
over vcan (slow)."""

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
    assert "#define POLICY_OBS_DIM 17" in header
    assert "#define POLICY_ACT_THIGH_TORQUE 0" in header


def test_a_walker_policy_in_lock_step_on_the_python_node(walker_export: Path, tmp_path: Path) -> None:
    _check_lock_step(hil(None, walker_export, tmp_path, "--node", "python", "--episodes", "3"), 3)


@pytest.mark.slow
def test_a_walker_policy_in_lock_step_on_the_c_node_over_vcan(
    guest: Guest, walker_export: Path, tmp_path: Path
) -> None:
    _check_lock_step(hil(guest, walker_export, tmp_path, "--episodes", "3"), 3)
