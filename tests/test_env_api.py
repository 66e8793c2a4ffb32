"""The environment's contract: checkers, spaces, determinism, start states, rendering, bad input."""

from __future__ import annotations

import math
import warnings

import gymnasium as gym
import numpy as np
import pytest
from gymnasium.utils.env_checker import check_env as gym_check_env
from stable_baselines3.common.env_checker import check_env as sb3_check_env

from embedrl import train
from embedrl.train import layout
from embedrl.train.warehouse_env import MAX_EPISODE_STEPS, WarehouseRobotEnv

Env = gym.Env[np.ndarray, np.ndarray]


def test_registered_with_time_limit() -> None:
    spec = gym.spec(train.ENV_ID)
    assert spec.max_episode_steps == MAX_EPISODE_STEPS == 200


def test_gymnasium_check_env_without_warnings() -> None:
    with warnings.catch_warnings(record=True) as caught:
        warnings.simplefilter("always")
        gym_check_env(gym.make(train.ENV_ID, render_mode="rgb_array").unwrapped)
    assert [str(w.message) for w in caught] == []


def test_sb3_check_env_without_warnings() -> None:
    with warnings.catch_warnings(record=True) as caught:
        warnings.simplefilter("always")
        sb3_check_env(gym.make(train.ENV_ID), warn=True)
    assert [str(w.message) for w in caught] == []


def test_spaces(env: Env) -> None:
    assert env.observation_space.shape == (6,) and env.observation_space.dtype == np.float32
    assert env.action_space.shape == (2,) and env.action_space.dtype == np.float32
    assert isinstance(env.action_space, gym.spaces.Box)
    assert np.all(env.action_space.low == -1.0) and np.all(env.action_space.high == 1.0)


def _rollout(env: Env, seed: int, actions: np.ndarray) -> list[bytes]:
    obs, _ = env.reset(seed=seed)
    out = [obs.tobytes()]
    for a in actions:
        obs, reward, terminated, truncated, _ = env.step(a)
        out.append(obs.tobytes() + np.float64(reward).tobytes())
        if terminated or truncated:
            break
    return out


def test_same_seed_and_actions_give_bit_identical_observations(env: Env) -> None:
    actions = np.random.default_rng(7).uniform(-1, 1, size=(200, 2)).astype(np.float32)
    first = _rollout(env, 123, actions)
    other = gym.make(train.ENV_ID)
    _rollout(other, 99, actions)  # a different history in the second instance must not matter
    assert _rollout(other, 123, actions) == first
    assert _rollout(env, 123, actions) == first  # the same instance, reset after an episode
    assert len(first) > 5


def test_different_seeds_give_different_starts(env: Env) -> None:
    starts = {env.reset(seed=s)[0].tobytes() for s in range(20)}
    assert len(starts) == 20


def test_start_states_are_beside_the_shelves_on_both_sides(env: Env) -> None:
    sides = set()
    for seed in range(100):
        obs, info = env.reset(seed=seed)
        x, y, s, c, v, w = (float(o) for o in obs)
        assert layout.START_X_MIN <= abs(x) <= layout.START_X_MAX
        assert layout.START_Y_MIN <= y <= layout.START_Y_MAX
        assert math.isclose(s * s + c * c, 1.0, rel_tol=1e-6)
        assert v == 0.0 and w == 0.0
        assert info == {"is_success": False, "collided": False, "collided_with": None}
        sides.add(x > 0)
    assert sides == {True, False}


def test_observations_stay_inside_the_observation_space(env: Env) -> None:
    rng = np.random.default_rng(1)
    for seed in range(20):
        obs, _ = env.reset(seed=seed)
        done = False
        while not done:
            obs, _, terminated, truncated, _ = env.step(rng.uniform(-1, 1, 2).astype(np.float32))
            assert env.observation_space.contains(obs), obs
            done = terminated or truncated


def test_start_pose_option(env: Env) -> None:
    obs, _ = env.reset(options={"start_pose": (0.5, 0.3, math.pi / 2)})
    np.testing.assert_allclose(obs, [0.5, 0.3, 1.0, 0.0, 0.0, 0.0], atol=1e-6)


@pytest.mark.parametrize(
    ("pose", "message"),
    [
        ((0.7, 0.0, 0.0), "overlaps right shelf$"),
        ((0.0, 0.75, 0.0), "overlaps upper shelf"),
        ((1.75, 0.5, 0.0), "overlaps right wall"),
        ((2.5, 0.5, 0.0), "outside the arena"),
        ((0.0, float("nan"), 0.0), "must be finite"),
        ((0.0, 0.3), "three numbers"),
        ("abc", "three numbers"),
    ],
)
def test_bad_start_pose_is_a_clear_error(env: Env, pose: object, message: str) -> None:
    with pytest.raises(ValueError, match=message):
        env.reset(options={"start_pose": pose})


def test_unknown_reset_option_is_an_error(env: Env) -> None:
    with pytest.raises(ValueError, match=r"unknown reset option.*'speed'"):
        env.reset(options={"speed": 2})


def test_step_before_reset_and_non_finite_actions_are_errors() -> None:
    raw = WarehouseRobotEnv()
    with pytest.raises(RuntimeError, match="reset"):
        raw.step(np.zeros(2, dtype=np.float32))
    raw.reset(seed=0)
    with pytest.raises(ValueError, match="finite"):
        raw.step(np.array([np.nan, 0.0], dtype=np.float32))


def test_actions_outside_the_box_are_clipped() -> None:
    a, b = WarehouseRobotEnv(), WarehouseRobotEnv()
    a.reset(seed=5)
    b.reset(seed=5)
    oa = a.step(np.array([3.0, -7.0], dtype=np.float32))
    ob = b.step(np.array([1.0, -1.0], dtype=np.float32))
    assert oa[0].tobytes() == ob[0].tobytes() and oa[1] == ob[1]


def test_rgb_array_frames_show_the_robot_moving() -> None:
    env = gym.make(train.ENV_ID, render_mode="rgb_array")
    env.reset(seed=0)
    first = env.render()
    assert isinstance(first, np.ndarray) and first.dtype == np.uint8
    assert first.ndim == 3 and first.shape[2] == 3 and first.shape[0] > 100 and first.shape[1] > 200
    for _ in range(3):
        env.step(np.array([1.0, 1.0], dtype=np.float32))
    later = env.render()
    assert isinstance(later, np.ndarray) and later.shape == first.shape
    assert np.count_nonzero(np.any(later != first, axis=2)) > 100


def test_unsupported_render_mode_is_an_error() -> None:
    with pytest.raises(ValueError, match="human"):
        WarehouseRobotEnv(render_mode="human")
