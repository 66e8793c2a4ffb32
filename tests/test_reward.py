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


# -- potential-based shaping (reward="shaped") --------------------------------------------------------


def test_way_to_goal_and_shaping_match_hand_computed_values() -> None:
    from embedrl.train import rewards

    # In the aisle: straight to the middle of the goal line (0, -0.15).
    assert rewards.way_to_goal(0.3, 0.25) == pytest.approx(math.hypot(0.3, 0.4), abs=1e-12)
    # Beside the shelves: to the aisle mouth (1.25, 0.32), then on to the goal.
    expected = math.hypot(1.5 - 1.25, 0.8 - 0.32) + math.hypot(1.25, 0.32 + 0.15)
    assert rewards.way_to_goal(1.5, 0.8) == pytest.approx(expected, abs=1e-12)
    assert rewards.way_to_goal(-1.5, 0.8) == pytest.approx(expected, abs=1e-12)
    # Phi = 3 m - way, positive everywhere in the arena.
    assert rewards.potential(0.3, 0.25) == pytest.approx(3.0 - 0.5, abs=1e-12)
    assert rewards.potential(1.5, 0.8) == pytest.approx(3.0 - expected, abs=1e-12)
    # gamma * Phi(s') - Phi(s); Phi = 0 after the last step.
    assert rewards.shaping(1.0, 1.5, False, 0.99) == pytest.approx(0.99 * 1.5 - 1.0)
    assert rewards.shaping(2.8, 2.9, True, 0.99) == pytest.approx(-2.8)


def test_a_collision_forfeits_the_potential_so_crashing_at_once_stays_costly() -> None:
    """The shaped trap, measured with Phi = -way: a crash landed on the goal's potential (0). With the
    offset, a crash from the start costs more than eq. 19's -2 and a step towards the goal earns."""
    from embedrl.train import rewards

    start = rewards.potential(1.5, 0.8)
    assert rewards.shaping(start, 0.0, True, 0.99) < -0.9
    closer = rewards.potential(1.4, 0.7)
    assert rewards.shaping(start, closer, False, 0.99) > 0.1


def _corridor_q(v: np.ndarray, potential: np.ndarray | None, gamma: float) -> np.ndarray:
    """One Bellman backup of Q (left, right) in a corridor of ``len(v)`` cells: the goal at the right
    end (+5), a pit at the left end (-2), -0.14 a step, shaped by ``potential`` if given; ``v`` the
    values of the cells after the step."""
    from embedrl.train import rewards

    n = len(v)
    q = np.zeros((n, 2))
    for s in range(1, n - 1):
        for a, nxt in enumerate((s - 1, s + 1)):
            terminal = nxt in (0, n - 1)
            r = -0.14 + (5.0 if nxt == n - 1 else -2.0 if nxt == 0 else 0.0)
            if potential is not None:
                r += rewards.shaping(potential[s], potential[nxt], terminal, gamma)
            q[s, a] = r + (0.0 if terminal else gamma * v[nxt])
    return q


def test_shaping_leaves_the_optimal_policy_of_a_small_mdp_unchanged() -> None:
    """A corridor of 6 cells, the goal at the right end (+5), a pit at the left end (-2), -0.14 a step,
    like the warehouse's economics; shaping from any potential keeps every state's best action."""
    from embedrl.train import rewards

    n, gamma = 6, 0.99
    rng = np.random.default_rng(0)

    def q_values(potential: np.ndarray | None) -> np.ndarray:
        q = np.zeros((n, 2))
        for _ in range(2000):
            v = q.max(axis=1)
            q = _corridor_q(v, potential, gamma)
        return q

    plain = q_values(None).argmax(axis=1)[1:-1]
    for _ in range(5):
        assert np.array_equal(q_values(rng.normal(0, 3, n)).argmax(axis=1)[1:-1], plain)
    # The warehouse's own potential, along a line towards the goal, too.
    line = np.array([rewards.potential(1.6 - 0.3 * k, 0.3) for k in range(n)])
    assert np.array_equal(q_values(line).argmax(axis=1)[1:-1], plain)


def test_the_shaped_env_reward_is_the_study_reward_plus_the_shaping_term() -> None:
    from embedrl.train import rewards

    env = gym.make("embedrl/WarehouseRobot-v0", reward="shaped")
    plain = gym.make("embedrl/WarehouseRobot-v0")
    rng = np.random.default_rng(1)
    for seed in range(3):
        env.reset(seed=seed)
        plain.reset(seed=seed)
        start = env.unwrapped.trajectory[0]  # type: ignore[attr-defined]
        phi = rewards.potential(start[0], start[1])
        done, plain_total = False, 0.0
        while not done:
            a = rng.uniform(-1, 1, 2).astype(np.float32)
            _, r, terminated, truncated, info = env.step(a)
            _, r_plain, *_ = plain.step(a)
            plain_total += float(r_plain)
            x, y, _theta = env.unwrapped.trajectory[-1]  # type: ignore[attr-defined]
            after = rewards.potential(x, y)
            expected = float(r_plain) + rewards.shaping(phi, after, terminated)
            assert float(r) == pytest.approx(expected, abs=1e-9)
            phi, done = after, terminated or truncated
        # What the study's criterion and the evaluations measure: the return without the shaping term.
        assert info["study_return"] == pytest.approx(plain_total, abs=1e-9)


def test_shaping_keeps_the_crash_early_trap_of_a_crashing_policy() -> None:
    """Why shaping alone does not lead out of the trap: it shifts every Q of *any* policy by -Phi(s)
    (Q'^pi = Q^pi - Phi), so under a policy that crashes, crashing at once still looks better than one
    step towards the goal, with or without shaping. Corridor as above, the policy always goes left."""
    from embedrl.train import rewards

    n, gamma = 6, 0.99

    def q_of_go_left(potential: np.ndarray | None) -> np.ndarray:
        v = np.zeros(n)
        for _ in range(200):  # policy evaluation of "always left"
            v = np.array(
                [0.0]
                + [
                    -0.14
                    + (-2.0 if s - 1 == 0 else 0.0)
                    + (
                        rewards.shaping(potential[s], potential[s - 1], s - 1 == 0, gamma)
                        if potential is not None
                        else 0.0
                    )
                    + (0.0 if s - 1 == 0 else gamma * v[s - 1])
                    for s in range(1, n - 1)
                ]
                + [0.0]
            )
        return _corridor_q(v, potential, gamma)

    plain = q_of_go_left(None)
    assert plain[1, 0] > plain[1, 1]  # the trap: beside the pit, falling in beats a step right
    line = np.array([rewards.potential(1.6 - 0.3 * k, 0.3, gain=5.0) for k in range(n)])
    shaped = q_of_go_left(line)
    np.testing.assert_allclose(shaped[1:-1], plain[1:-1] - line[1:-1, None], atol=1e-9)
    assert shaped[1, 0] > shaped[1, 1]
