"""The reference study's reward, against hand-computed values and inside the env."""

from __future__ import annotations

import math

import gymnasium as gym
import numpy as np
import pytest

from embedrl.train import layout
from embedrl.train.warehouse_env import SUCCESS_BONUS, reward

A = np.array


@pytest.mark.parametrize(
    ("x", "y", "w", "action", "made_it", "collided", "expected"),
    [
        # 0.06 + 0.05 - 0.14
        (0.0, 0.0, 0.0, A([0.0, 0.0]), False, False, -0.03),
        # 0.06 e^-3 + 0.05 e^-2 - 0.14 - 0.001*4 - 0.01*2
        (0.5, 1.0, 2.0, A([1.0, -1.0]), False, False, -0.1542460117),
        # 0.06 e^0.45 + 0.05 - 0.14 - 0.01*2 + 5
        (0.0, -0.15, 0.0, A([1.0, 1.0]), True, False, 4.9840987311),
        # 0.06 e^-0.9 + 0.05 e^-8 - 0.14 - 0.001 - 0.01*0.5 - 2
        (-1.0, 0.3, -1.0, A([0.5, 0.5]), False, True, -2.1215890472),
    ],
)
def test_reward_matches_hand_computed_values(
    x: float, y: float, w: float, action: np.ndarray, made_it: bool, collided: bool, expected: float
) -> None:
    assert reward(x, y, w, action, made_it, collided) == pytest.approx(expected, abs=1e-9)


def test_env_reward_is_the_formula_on_the_observation_after_the_step(
    env: gym.Env[np.ndarray, np.ndarray],
) -> None:
    rng = np.random.default_rng(3)
    checked = 0
    for seed in range(5):
        env.reset(seed=seed)
        done = False
        while not done:
            a = rng.uniform(-1, 1, 2).astype(np.float32)
            obs, r, terminated, truncated, info = env.step(a)
            expected = reward(
                float(obs[0]), float(obs[1]), float(obs[5]), a, info["is_success"], info["collided"]
            )
            assert r == expected
            checked += 1
            done = terminated or truncated
    assert checked > 50


def test_waiting_in_the_gap_never_pays_more_than_driving_through() -> None:
    # The best non-terminal step anywhere the robot centre can be: at the goal line, centred, at rest.
    best_step = reward(0.0, layout.GOAL_Y, 0.0, A([0.0, 0.0]), False, False)
    assert best_step == pytest.approx(0.06 * math.exp(0.45) + 0.05 - 0.14)
    assert 0.0 < best_step < 0.005
    assert 200 * best_step < SUCCESS_BONUS / 4
