"""Episodes end as documented: collisions with every obstacle, success through the gap, truncation."""

from __future__ import annotations

import math
from typing import Any

import gymnasium as gym
import numpy as np
import pytest

from embedrl.train import layout
from embedrl.train.warehouse_env import (
    COLLISION_PENALTY,
    MAX_EPISODE_STEPS,
    SUCCESS_BONUS,
    WarehouseRobotEnv,
    reward,
)

Env = gym.Env[np.ndarray, np.ndarray]
FULL_AHEAD = np.array([1.0, 1.0], dtype=np.float32)
UP, DOWN, LEFT, RIGHT = math.pi / 2, -math.pi / 2, math.pi, 0.0

# A start pose facing each obstacle, close enough to reach it at full force within a few steps.
COLLISION_STARTS = {
    "left shelf": (-0.7, 0.2, DOWN),
    "right shelf": (0.7, 0.2, DOWN),
    "upper shelf": (0.0, 0.4, UP),
    "left wall": (-1.5, 0.3, LEFT),
    "right wall": (1.5, 0.3, RIGHT),
    "top wall": (1.5, 1.0, UP),
    "bottom left wall": (-1.45, 0.2, DOWN),
    "bottom right wall": (1.45, 0.2, DOWN),
}


def drive(
    env: Env, action: np.ndarray, max_steps: int
) -> tuple[int, np.ndarray, float, bool, bool, dict[str, Any]]:
    """Step with a constant action until the episode ends or ``max_steps``; the last step's results."""
    step = 0
    while True:
        step += 1
        obs, r, terminated, truncated, info = env.step(action)
        if terminated or truncated or step == max_steps:
            break
    return step, obs, float(r), terminated, truncated, info


def test_every_obstacle_has_a_collision_case() -> None:
    assert set(COLLISION_STARTS) == {r.name for r in layout.OBSTACLES}


@pytest.mark.parametrize("name", sorted(COLLISION_STARTS))
def test_collision_terminates_with_the_penalty(env: Env, name: str) -> None:
    env.reset(options={"start_pose": COLLISION_STARTS[name]})
    step, obs, r, terminated, truncated, info = drive(env, FULL_AHEAD, 10)
    assert terminated and not truncated, f"no collision with the {name} after {step} steps"
    study_return = info.pop("study_return")
    assert info == {"is_success": False, "collided": True, "collided_with": name}
    assert r == reward(float(obs[0]), float(obs[1]), float(obs[5]), FULL_AHEAD, False, True)
    assert r < -COLLISION_PENALTY
    # Steps before the collision carry no penalty; the episode's return is every step's reward.
    env.reset(options={"start_pose": COLLISION_STARTS[name]})
    total = 0.0
    for _ in range(step - 1):
        r_before = env.step(FULL_AHEAD)[1]
        assert float(r_before) > -0.2
        total += float(r_before)
    assert study_return == pytest.approx(total + r, abs=1e-9)


def test_driving_down_through_the_gap_succeeds_with_the_bonus(env: Env) -> None:
    env.reset(options={"start_pose": (0.0, 0.3, DOWN)})
    _, obs, r, terminated, truncated, info = drive(env, FULL_AHEAD, 10)
    assert terminated and not truncated
    assert SUCCESS_BONUS - 2.0 < info.pop("study_return") < r  # a few steps of -0.14 before the bonus
    assert info == {"is_success": True, "collided": False, "collided_with": None}
    assert r == reward(float(obs[0]), float(obs[1]), float(obs[5]), FULL_AHEAD, True, False)
    assert r > SUCCESS_BONUS - 0.2
    assert obs[1] == pytest.approx(layout.GOAL_Y, abs=1e-6)  # y is reported clipped at the goal line


def test_standing_still_is_truncated_at_200_steps(env: Env) -> None:
    env.reset(seed=0)
    step, _, _, terminated, truncated, info = drive(env, np.zeros(2, dtype=np.float32), 1000)
    assert step == MAX_EPISODE_STEPS and truncated and not terminated
    assert info["is_success"] is False and info["collided"] is False


def test_the_unwrapped_env_truncates_on_its_own() -> None:
    raw = WarehouseRobotEnv()
    raw.reset(seed=0)
    stop = np.zeros(2, dtype=np.float32)
    results = [raw.step(stop) for _ in range(MAX_EPISODE_STEPS)]
    assert [r[3] for r in results].index(True) == MAX_EPISODE_STEPS - 1
