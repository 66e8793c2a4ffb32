"""The moving-shelf and two-robot scenarios: API checkers, seeds, the moving shelf's motion and wrap-around,
contacts between robots, the potential-field reward at the corners and the parameter-sharing vector env."""

from __future__ import annotations

import csv
import json
import math
from pathlib import Path

import gymnasium as gym
import numpy as np
import pytest
from gymnasium.utils.env_checker import check_env
from pettingzoo.test import parallel_api_test, parallel_seed_test

import embedrl.train  # noqa: F401 (registers the envs)
from embedrl.cli import main
from embedrl.train import layout, rewards
from embedrl.train.config import Budget
from embedrl.train.moving_shelf_env import WarehouseMovingShelfEnv
from embedrl.train.robot import PHYSICS_SUBSTEPS, SAMPLE_TIME
from embedrl.train.scenarios import MOVING_SHELF, SCENARIOS, TWO_ROBOTS
from embedrl.train.shared_policy import SharedPolicyVecEnv
from embedrl.train.trainer import train
from embedrl.train.two_robots_env import AGENTS, WarehouseTwoRobotsEnv, parallel_env

STOP = np.zeros(2, dtype=np.float32)
AHEAD = np.ones(2, dtype=np.float32)


def _run(env: gym.Env[np.ndarray, np.ndarray], seed: int, steps: int = 60) -> list[np.ndarray]:
    rng = np.random.default_rng(seed)
    obs, _ = env.reset(seed=seed)
    out = [obs]
    for _ in range(steps):
        obs, r, terminated, truncated, _ = env.step(rng.uniform(-1, 1, 2).astype(np.float32))
        out.append(np.append(obs, float(r)))
        if terminated or truncated:
            break
    return out


# -- moving shelf ---------------------------------------------------------------------------------


def test_moving_shelf_env_passes_gymnasium_checker() -> None:
    check_env(WarehouseMovingShelfEnv(), skip_render_check=True)
    env = gym.make(MOVING_SHELF.env_id)
    assert env.observation_space.shape == (len(MOVING_SHELF.observation),) == (9,)
    np.testing.assert_array_equal(env.observation_space.low, MOVING_SHELF.obs_low)  # type: ignore[attr-defined]


@pytest.mark.parametrize("reward", rewards.REWARDS)
def test_moving_shelf_same_seed_same_episode(reward: str) -> None:
    a, b = gym.make(MOVING_SHELF.env_id, reward=reward), gym.make(MOVING_SHELF.env_id, reward=reward)
    for seed in (0, 7, 123):
        first, second = _run(a, seed), _run(b, seed)
        assert len(first) == len(second)
        for x, y in zip(first, second, strict=True):
            np.testing.assert_array_equal(x, y)
    assert not np.array_equal(_run(a, 1)[0], _run(a, 2)[0])


def test_the_shelf_moves_at_its_speed_and_is_observed_relative_to_the_robot() -> None:
    env = gym.make(MOVING_SHELF.env_id)
    obs, _ = env.reset(options={"start_pose": (-1.5, 0.2, 0.0), "shelf": (0.0, 0.6, 0.2)})
    assert obs[6:] == pytest.approx([1.5, 0.4, 0.2], abs=1e-6)
    for k in range(1, 4):
        obs, *_ = env.step(STOP)
        # The robot stands still; the shelf's centre moves 0.2 m/s * 0.3 s per step.
        assert obs[6] - (-1.5 - float(obs[0])) == pytest.approx(1.5 + 0.2 * SAMPLE_TIME * k, abs=1e-5)
        assert obs[7] == pytest.approx(0.6 - float(obs[1]), abs=1e-6)


@pytest.mark.parametrize("vx", [0.45, -0.45])
def test_the_shelf_leaving_at_one_side_reappears_at_the_other(vx: float) -> None:
    env = gym.make(MOVING_SHELF.env_id)
    start = math.copysign(layout.MOVING_SHELF_WRAP_X - 0.01, vx)
    obs, _ = env.reset(options={"start_pose": (0.0, 0.2, 0.0), "shelf": (start, 0.6, vx)})
    centre = float(obs[0] + obs[6])
    obs, *_ = env.step(STOP)
    moved = vx * SAMPLE_TIME  # 0.075 m, past the wrap line: it re-enters at the other side
    expected = start + moved - math.copysign(2 * layout.MOVING_SHELF_WRAP_X, vx)
    assert centre == pytest.approx(start, abs=1e-5)
    assert float(obs[0] + obs[6]) == pytest.approx(expected, abs=1e-5)
    assert float(obs[8]) == pytest.approx(vx)
    # It keeps its speed and height after the wrap.
    obs, *_ = env.step(STOP)
    assert float(obs[0] + obs[6]) == pytest.approx(expected + moved, abs=1e-5)
    assert float(obs[1] + obs[7]) == pytest.approx(0.6, abs=1e-6)


def test_a_robot_standing_in_the_shelf_path_is_hit() -> None:
    env = gym.make(MOVING_SHELF.env_id)
    env.reset(options={"start_pose": (1.0, 0.75, math.pi / 2), "shelf": (-0.6, 0.6, 0.25)})
    for _ in range(60):
        _, r, terminated, truncated, info = env.step(STOP)
        if terminated or truncated:
            break
    assert terminated and info["collided"] and info["collided_with"] == "moving shelf"
    assert not info["is_success"] and float(r) < -2.0


def test_every_start_leaves_the_robot_time_to_get_out_of_the_way() -> None:
    env = WarehouseMovingShelfEnv()
    for seed in range(300):
        obs, _ = env.reset(seed=seed)
        shelf = layout.moving_shelf(float(obs[0] + obs[6]), float(obs[1] + obs[7]))
        assert shelf.distance(float(obs[0]), float(obs[1]))[0] >= layout.MOVING_SHELF_START_CLEARANCE - 1e-6
        # A robot that stands still is not touched for at least the start lead (2.5 s).
        world = env._world
        assert world is not None
        for _ in range(round(layout.MOVING_SHELF_START_LEAD / SAMPLE_TIME) - 1):
            for _ in range(PHYSICS_SUBSTEPS):
                world.substep([STOP])
        assert world.hits[0] is None, seed
        assert layout.MOVING_SHELF_Y_MIN <= obs[1] + obs[7] <= layout.MOVING_SHELF_Y_MAX + 1e-6
        assert layout.MOVING_SHELF_SPEED_MIN - 1e-6 <= abs(obs[8]) <= layout.MOVING_SHELF_SPEED_MAX + 1e-6


@pytest.mark.parametrize(
    "shelf", [(0.0, 0.4, 0.1), (0.0, 0.6, 0.5), (3.5, 0.6, 0.1), (math.nan, 0.6, 0.1), (1.0, 0.6)]
)
def test_a_bad_shelf_option_is_refused(shelf: tuple[float, ...]) -> None:
    with pytest.raises(ValueError, match="shelf"):
        WarehouseMovingShelfEnv().reset(options={"start_pose": (-1.5, 0.2, 0.0), "shelf": shelf})


# -- the potential-field reward -------------------------------------------------------------------


def test_field_at_a_point_matches_hand_computed_values() -> None:
    box = layout.Rect("box", 0.0, 0.0, 1.0, 1.0)
    # A point 0.05 m to the right of the box: 0.06 e^-1.5 + 0.05 e^-(8 * 1.05^2) - 0.05 e^-1.
    expected = 0.06 * math.exp(-1.5) + 0.05 * math.exp(-8.82) - 0.05 * math.exp(-1.0)
    assert rewards.field(1.05, 0.5, [box]) == pytest.approx(expected, abs=1e-12)
    # Inside an obstacle the contour is at its deepest, -0.05.
    assert rewards.field(0.5, 0.5, [box]) == pytest.approx(
        0.06 * math.exp(-1.5) + 0.05 * math.exp(-2.0) - 0.05, abs=1e-12
    )
    # Another robot at (0, 0), heading along x: a point 0.1 m ahead of its front (x = 0.125 + 0.1).
    assert rewards.field(0.225, 0.0, [], [(0.0, 0.0, 0.0)]) == pytest.approx(
        0.06 + 0.05 * math.exp(-8 * 0.225**2) - 0.05 * math.exp(-2.0), abs=1e-12
    )


def test_the_step_reward_averages_the_field_over_the_four_corners() -> None:
    box = layout.Rect("box", 0.5, -1.0, 1.0, 1.0)
    pose = (0.0, 0.0, 0.0)  # corners at x = +-0.125, y = +-0.1
    corners = [(-0.125, -0.1), (0.125, -0.1), (0.125, 0.1), (-0.125, 0.1)]
    terms = [
        0.06 * math.exp(-3 * y) + 0.05 * math.exp(-8 * x * x) - 0.05 * math.exp(-(0.5 - x) / 0.05)
        for x, y in corners
    ]
    action = np.array([0.5, -1.0])
    expected = sum(terms) / 4 - 0.14 - 0.001 * 0.25 - 0.01 * 1.25 + 20.0
    got = rewards.potential_field(pose, 0.5, action, True, False, [box], bonus=20.0)
    assert got == pytest.approx(expected, abs=1e-12)
    assert rewards.potential_field(pose, 0.5, action, False, True, [box]) == pytest.approx(
        sum(terms) / 4 - 0.14 - 0.001 * 0.25 - 0.01 * 1.25 - 2.0, abs=1e-12
    )
    # A corner near an obstacle is felt although the centre is 0.5 m away: turning towards it costs.
    turned = rewards.potential_field((0.25, 0.0, 0.0), 0.0, np.zeros(2), False, False, [box])
    assert turned < rewards.potential_field((0.0, 0.0, 0.0), 0.0, np.zeros(2), False, False, [box]) - 0.005


def test_the_moving_shelf_env_rewards_with_the_shelf_where_it_is() -> None:
    env = WarehouseMovingShelfEnv(reward="potential-field")
    env.reset(options={"start_pose": (-1.5, 0.3, 0.0), "shelf": (0.0, 0.6, 0.2)})
    _, r, *_ = env.step(STOP)
    world = env._world
    assert world is not None
    shelf = world.shelf_rect()
    assert shelf is not None and shelf.x0 == pytest.approx(-1.1 + 0.06, abs=1e-9)
    pose = world.pose(0)
    expected = rewards.potential_field(
        pose, float(world.robots[0].angular_velocity), STOP, False, False, (*layout.FIXED_OBSTACLES, shelf)
    )
    assert r == pytest.approx(expected, abs=1e-6)


# -- two robots -----------------------------------------------------------------------------------


def test_two_robot_env_passes_pettingzoo_api_and_seed_tests() -> None:
    parallel_api_test(WarehouseTwoRobotsEnv(), num_cycles=400)
    parallel_seed_test(parallel_env)
    env = WarehouseTwoRobotsEnv()
    for agent in AGENTS:
        assert env.observation_space(agent).shape == (len(TWO_ROBOTS.observation),) == (12,)


def test_two_robot_partner_view_passes_gymnasium_checker() -> None:
    env = gym.make(TWO_ROBOTS.env_id)
    check_env(env.unwrapped, skip_render_check=True)


def test_two_robots_same_seed_same_episode() -> None:
    def episode(seed: int) -> list[tuple[str, np.ndarray]]:
        env = WarehouseTwoRobotsEnv(reward="potential-field")
        rng = np.random.default_rng(seed)
        obs, _ = env.reset(seed=seed)
        out = [(a, o) for a, o in obs.items()]
        while env.agents:
            obs, rew, *_ = env.step({a: rng.uniform(-1, 1, 2) for a in env.agents})
            out += [(a, np.append(o, rew[a])) for a, o in obs.items()]
        return out

    for seed in (0, 5):
        first, second = episode(seed), episode(seed)
        assert [a for a, _ in first] == [a for a, _ in second]
        for (_, x), (_, y) in zip(first, second, strict=True):
            np.testing.assert_array_equal(x, y)


def test_starts_put_the_robots_on_opposite_sides() -> None:
    env = WarehouseTwoRobotsEnv()
    sides = set()
    for seed in range(50):
        obs, _ = env.reset(seed=seed)
        x0, x1 = float(obs["robot_0"][0]), float(obs["robot_1"][0])
        assert x0 * x1 < 0 and layout.START_X_MIN - 1e-6 <= abs(x0) <= layout.START_X_MAX + 1e-6
        assert obs["robot_0"][6] == pytest.approx(x1 - x0, abs=1e-5) and obs["robot_0"][11] == 1.0
        sides.add(x0 > 0)
    assert sides == {True, False}


def test_robots_driving_into_each_other_end_the_episode_for_both() -> None:
    env = WarehouseTwoRobotsEnv()
    env.reset(options={"start_poses": ((-0.4, 0.35, 0.0), (0.4, 0.35, math.pi))})
    for _ in range(10):
        _, rew, term, trunc, infos = env.step({a: AHEAD for a in env.agents})
        if not env.agents:
            break
    assert env.agents == []
    assert term == {"robot_0": True, "robot_1": True} and trunc == {"robot_0": False, "robot_1": False}
    assert infos["robot_0"]["collided_with"] == "robot 1" and infos["robot_1"]["collided_with"] == "robot 0"
    assert env.outcomes == ["collision", "collision"] and all(r < -2.0 for r in rew.values())


def test_a_crash_stops_the_other_robot_without_penalty() -> None:
    env = WarehouseTwoRobotsEnv()
    env.reset(options={"start_poses": ((-1.5, 0.3, math.pi), (1.5, 0.3, math.pi / 2))})
    for _ in range(10):
        _, rew, term, trunc, infos = env.step({"robot_0": AHEAD, "robot_1": STOP})
        if not env.agents:
            break
    assert infos["robot_0"]["collided_with"] == "left wall" and term["robot_0"]
    assert trunc["robot_1"] and not term["robot_1"] and env.outcomes == ["collision", "stopped"]
    assert rew["robot_1"] > -0.2  # no collision penalty for the robot that did nothing wrong


def test_a_robot_through_the_gap_leaves_and_the_other_goes_on() -> None:
    env = WarehouseTwoRobotsEnv()
    env.reset(options={"start_poses": ((0.0, 0.05, -math.pi / 2), (1.5, 0.3, math.pi / 2))})
    through = None
    for step in range(10):
        obs, rew, term, _, infos = env.step({a: (AHEAD if a == "robot_0" else STOP) for a in env.agents})
        if term.get("robot_0"):
            through = step
            assert infos["robot_0"]["is_success"] and rew["robot_0"] > 4.0
            break
    assert through is not None and env.agents == ["robot_1"]
    world = env._world
    assert world is not None and world.active == [False, True]
    obs, *_ = env.step({"robot_1": STOP})
    np.testing.assert_array_equal(obs["robot_1"][6:], np.zeros(6, dtype=np.float32))  # the other is gone


def test_shared_policy_vec_env_one_slot_per_robot_with_absorbing_states() -> None:
    venv = SharedPolicyVecEnv(WarehouseTwoRobotsEnv())
    venv.seed(3)
    obs = np.asarray(venv.reset())
    assert venv.num_envs == 2 and obs.shape == (2, 12)
    env = venv.env
    env.reset(options={"start_poses": ((0.0, 0.05, -math.pi / 2), (1.5, 0.3, math.pi / 2))})
    venv._start = lambda: np.zeros((2, 12), dtype=np.float32)  # type: ignore[method-assign]
    done_at = None
    for step in range(12):
        stepped, rew, dones, infos = venv.step(np.stack([AHEAD, STOP]))
        obs = np.asarray(stepped)
        if done_at is None and dones[0]:
            done_at = step
            assert infos[0]["is_success"] and "episode" in infos[0] and not infos[0]["TimeLimit.truncated"]
            assert not dones[1]
            np.testing.assert_array_equal(obs[0], np.zeros(12))  # the absorbing state
        elif done_at is not None:
            assert rew[0] == 0.0 and not dones[0] and obs[0].sum() == 0.0
    assert done_at is not None


def test_potential_field_controller_meets_the_bar_in_each_scenario() -> None:
    from embedrl.train.evaluate import evaluate
    from embedrl.train.potential_field import PotentialFieldController

    for spec in (MOVING_SHELF, TWO_ROBOTS):
        report = evaluate(PotentialFieldController(scenario=spec.name), 200, 0, spec.name, env_id=spec.env_id)
        assert report.success_rate >= 0.95, spec.name
        assert report.successes + report.collisions + report.timeouts == 200


def test_physics_substeps_are_shared() -> None:
    # One world module for every scenario: the step is the same 6 physics steps of 0.05 s.
    from embedrl.train.world import DT

    assert pytest.approx(SAMPLE_TIME) == DT * PHYSICS_SUBSTEPS


# -- training and the benchmark in the new scenarios ------------------------------------------------


@pytest.mark.slow
@pytest.mark.parametrize(
    ("scenario", "algo"),
    [("moving-shelf", "td3"), ("moving-shelf", "ppo"), ("two-robots", "sac"), ("two-robots", "ppo")],
)
def test_short_run_in_a_scenario_loads_and_evaluates(scenario: str, algo: str, tmp_path: Path) -> None:
    run = tmp_path / "run"
    overrides = ["learning_starts=200", "demonstrations=2"] if algo != "ppo" else ["n_steps=256"]
    summary = train(
        algo, "tuned", 0, run, Budget(max_steps=800, eval_every=400), overrides=overrides, scenario=scenario
    )
    assert summary["scenario"] == scenario and summary["updates"] > 0  # real updates, PPO's included
    # PPO keeps its behaviour-cloned start, and its updates changed it.
    assert (run / "warm_start_model.zip").is_file() == (algo == "ppo")
    if algo == "ppo":
        from stable_baselines3 import PPO

        obs = np.random.default_rng(0).uniform(-0.5, 0.5, (64, len(SCENARIOS[scenario].observation)))
        cloned, tuned = (PPO.load(run / f"{n}.zip", device="cpu") for n in ("warm_start_model", "last_model"))
        a, b = (m.predict(obs.astype(np.float32), deterministic=True)[0] for m in (cloned, tuned))
        assert np.abs(a - b).max() > 1e-4
    config = json.loads((run / "config.json").read_text())
    assert config["scenario"] == scenario
    rows = list(csv.DictReader((run / "curve.csv").open()))
    assert len(rows) == summary["total_episodes"] > 0
    robots = {r["robot"] for r in rows}
    assert robots == ({"0", "1"} if scenario == "two-robots" else {"0"})
    out = tmp_path / "eval.json"
    args = ["eval", str(run / "model.zip"), "--scenario", scenario, "--episodes", "3", "--json", str(out)]
    assert main(args) == 0
    report = json.loads(out.read_text())
    assert report["episodes"] == 3 and report["env_id"] == SCENARIOS[scenario].env_id
    if scenario == "two-robots":
        assert all(len(e["robots"]) == 2 for e in report["per_episode"])
    # A model of one scenario is refused in another, in one line.
    assert main(["eval", str(run / "model.zip"), "--episodes", "1"]) == 2


def test_thesis_preset_uses_the_potential_field_reward_outside_the_static_scenario() -> None:
    from embedrl.train.config import preset

    assert preset("ddpg", "thesis").reward == "thesis"
    assert preset("ddpg", "thesis", "moving-shelf").reward == "potential-field"
    assert preset("td3", "tuned", "two-robots").reward == "thesis"
    with pytest.raises(ValueError, match="scenario"):
        preset("td3", "tuned", "three-robots")


@pytest.mark.slow
def test_bench_in_the_two_robot_scenario_writes_all_rows(tmp_path: Path) -> None:
    args = ["bench", "--scenario", "two-robots", "--algos", "td3", "--seeds", "1", "--out", str(tmp_path)]
    args += ["--max-steps", "600", "--eval-episodes", "3", "--workers", "1", "--preset", "thesis"]
    assert main([*args, "--set", "success_bonus=20"]) == 0
    table = (tmp_path / "bench.md").read_text()
    for label in ("TD3 (ours)", "TD3 (study)", "reliability per seed (%)", "Scenario `two-robots`"):
        assert label in table
    assert "preset `thesis` with success_bonus=20" in table
    data = json.loads((tmp_path / "bench.json").read_text())
    assert data["scenario"] == "two-robots" and data["runs"][0]["scenario"] == "two-robots"
    config = json.loads((tmp_path / "runs" / "td3-seed0" / "config.json").read_text())
    assert config["hyperparameters"]["success_bonus"] == 20.0
    assert config["hyperparameters"]["reward"] == "potential-field"  # the study's two-robot reward
    assert data["potential_field"]["success_rate"] == 1.0  # the baseline on the same 3 episodes


def test_the_partially_observed_moving_shelf_is_the_moving_shelf_without_its_velocity() -> None:
    from embedrl.train.scenarios import MOVING_SHELF, MOVING_SHELF_PARTIAL

    full, partial = gym.make(MOVING_SHELF.env_id), gym.make(MOVING_SHELF_PARTIAL.env_id)
    kept = [i for i, f in enumerate(MOVING_SHELF.observation) if f.name != "shelf_vx"]
    assert [f.name for f in MOVING_SHELF_PARTIAL.observation] == [
        MOVING_SHELF.observation[i].name for i in kept
    ]
    for seed in range(3):
        a, _ = full.reset(seed=seed)
        b, _ = partial.reset(seed=seed)
        assert partial.observation_space.contains(b) and np.array_equal(a[kept], b)
        for _ in range(5):
            action = np.array([0.4, 0.3], np.float32)
            a, ra, *_ = full.step(action)
            b, rb, *_ = partial.step(action)
            assert np.array_equal(a[kept], b) and ra == rb
        teacher = partial.unwrapped.full_observation()  # type: ignore[attr-defined]
        assert np.array_equal(np.asarray(teacher, np.float32), a)
