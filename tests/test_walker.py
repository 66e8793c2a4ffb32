"""The deck's walking robot: its reward term by term against hand-computed values, the env's API, and the
contract (spec -> env spaces, docstring tables, CAN database) derived from its scenario spec."""

from __future__ import annotations

import pickle
import re
from pathlib import Path

import gymnasium as gym
import numpy as np
import pytest
from gymnasium.utils.env_checker import check_env

from embedrl.export.contract.dbc import database
from embedrl.export.contract.layout import layout
from embedrl.export.contract.sources import c_sources
from embedrl.hil.codec import Codec
from embedrl.train import deck_reward
from embedrl.train.deck_reward import TERMS, VARIANTS, DeckReward
from embedrl.train.scenarios import SCENARIOS, WALKER
from embedrl.train.walker_env import EPISODE_S, FALL, DeckWalkerEnv
from tests.test_interface import _table

Ts, Tf = 0.008, 8.0


def test_each_term_of_the_deck_reward_against_hand_computed_values() -> None:
    u = np.array([0.5, -0.5, 0.0, 0.0, 1.0, 0.0])
    terms = DeckReward().terms(v_x=0.7, y=0.2, z_hat=-0.1, previous_action=u, sample_time=Ts, episode_s=Tf)
    # v_x; -3 * 0.2^2; -50 * 0.1^2; 25 * 0.008 / 8; -0.02 * (0.25 + 0.25 + 1)
    expected = {"forward": 0.7, "path": -0.12, "height": -0.5, "survive": 0.025, "effort": -0.03}
    assert terms.keys() == expected.keys() and tuple(terms) == TERMS
    for term, value in expected.items():
        assert terms[term] == pytest.approx(value, abs=1e-12), term


@pytest.mark.parametrize(
    ("name", "kept"),
    [
        ("velocity", {"forward"}),
        ("upright", {"forward", "height", "survive"}),
        ("effort", {"forward", "height", "survive", "effort"}),
        ("deck", set(TERMS)),
    ],
)
def test_the_four_shaping_stages_keep_the_deck_s_terms(name: str, kept: set[str]) -> None:
    terms = VARIANTS[name].terms(1.0, 1.0, 1.0, np.ones(6), Ts, Tf)
    assert {t for t, v in terms.items() if v != 0.0} == kept
    assert list(VARIANTS) == ["velocity", "upright", "effort", "deck"]
    with pytest.raises(ValueError, match="not one of velocity, upright, effort, deck"):
        deck_reward.variant("thesis")


def test_the_env_reward_is_the_deck_formula_on_the_simulation() -> None:
    """Two steps by hand: v_x from the trunk's x over the step, z_hat from the height after reset, the
    survive bonus 25 Ts/Tf, the effort on the previous action (none before the first)."""
    env = DeckWalkerEnv()
    env.reset(seed=5)
    data = env._sim.unwrapped.data  # type: ignore[attr-defined]
    x0, z0 = float(data.qpos[0]), float(data.qpos[1])
    a1 = np.array([0.3, -0.2, 0.1, 0.0, 0.5, -0.4], dtype=np.float32)
    a2 = np.array([-0.6, 0.2, 0.0, 0.9, 0.0, 0.1], dtype=np.float32)
    _, r1, *_ = env.step(a1)
    x1, z1 = float(data.qpos[0]), float(data.qpos[1])
    assert r1 == pytest.approx((x1 - x0) / Ts - 50 * (z1 - z0) ** 2 + 25 * Ts / Tf, abs=1e-9)
    _, r2, _, _, info = env.step(a2)
    x2, z2 = float(data.qpos[0]), float(data.qpos[1])
    effort = 0.02 * float(np.sum(a1.astype(np.float64) ** 2))
    assert r2 == pytest.approx((x2 - x1) / Ts - 50 * (z2 - z0) ** 2 + 25 * Ts / Tf - effort, abs=1e-9)
    assert info["reward_effort"] == pytest.approx(-effort) and info["reward_path"] == 0.0
    assert info["study_return"] == pytest.approx(r1 + r2, abs=1e-12)
    assert sum(info[f"episode_{t}"] for t in TERMS) == pytest.approx(r1 + r2, abs=1e-12)
    assert info["distance"] == pytest.approx(x2 - x0) and Tf == EPISODE_S


def test_a_fall_ends_the_episode_without_the_survive_bonus_and_counts_as_a_collision() -> None:
    env = DeckWalkerEnv()
    env.reset(seed=0)
    path_terms, steps = [], 0
    terminated = truncated = False
    while not (terminated or truncated):  # no torque: the walker sinks
        _, _, terminated, truncated, info = env.step(np.zeros(6, dtype=np.float32))
        path_terms.append(info["reward_path"])
        steps += 1
    assert terminated and not truncated and steps < 300, steps
    assert info["collided"] and info["collided_with"] == FALL and not info["is_success"]
    assert info["reward_survive"] == 0.0 and info["episode_survive"] == pytest.approx(
        25 * Ts / Tf * (steps - 1)
    )
    assert set(path_terms) == {0.0}  # the planar walker never leaves its line


@pytest.mark.parametrize("reward", list(VARIANTS))
def test_gymnasium_check_env_passes(reward: str) -> None:
    env = gym.make(WALKER.env_id, reward=reward)
    check_env(env.unwrapped, skip_render_check=True)  # rendering needs an OpenGL context


def test_same_seed_same_episode_and_a_pickled_env_goes_on_the_same() -> None:
    actions = np.random.default_rng(1).uniform(-1, 1, (30, 6)).astype(np.float32)
    runs = []
    for _ in range(2):
        env = DeckWalkerEnv()
        first, _ = env.reset(seed=11)
        runs.append([first.tobytes(), *(env.step(a)[0].tobytes() for a in actions[:10])])
    assert runs[0] == runs[1]
    copy = pickle.loads(pickle.dumps(env))
    assert [copy.step(a)[0].tobytes() for a in actions[10:]] == [
        env.step(a)[0].tobytes() for a in actions[10:]
    ]
    with pytest.raises(ValueError, match="6 finite numbers"):
        env.step(np.full(6, np.nan, dtype=np.float32))
    with pytest.raises(RuntimeError, match="reset"):
        DeckWalkerEnv().step(np.zeros(6, dtype=np.float32))


def test_the_spec_matches_walker2d_v5_and_the_env() -> None:
    env = gym.make(WALKER.env_id)
    assert env.unwrapped._sim.unwrapped.dt == WALKER.sample_time_s  # type: ignore[attr-defined]
    assert env.spec is not None and env.spec.max_episode_steps == WALKER.max_steps
    assert SCENARIOS["walker"] is WALKER
    np.testing.assert_array_equal(env.observation_space.low, WALKER.obs_low)  # type: ignore[attr-defined]
    np.testing.assert_array_equal(env.action_space.high, WALKER.act_high)  # type: ignore[attr-defined]
    plain = gym.make("Walker2d-v5")
    assert plain.observation_space.shape == (len(WALKER.observation),)
    assert plain.action_space.shape == (len(WALKER.action),)
    doc = DeckWalkerEnv.__doc__ or ""
    rows = _table(doc, "Observation Space")
    assert [(r[1], float(r[2]), float(r[3]), r[4]) for r in rows] == [
        (f.description, f.low, f.high, f.unit) for f in WALKER.observation
    ]
    actions = _table(doc, "Action Space")
    assert [(r[1], float(r[2]), float(r[3])) for r in actions] == [
        (f.description, f.low, f.high) for f in WALKER.action
    ]
    assert f"{WALKER.max_steps} steps" in doc and f"({WALKER.sample_time_s} s)" in doc


def test_the_can_database_carries_17_observations_in_9_frames_and_6_actions_in_3() -> None:
    plan = layout(WALKER)
    assert [name for name, _, _ in plan.observation] == [f"Observation{c}" for c in "ABCDEFGHI"]
    assert [name for name, _, _ in plan.action] == ["ActionA", "ActionB", "ActionC"]
    assert [s.field.name for s in plan.observation_slots] == [f.name for f in WALKER.observation]
    assert [s.field.name for s in plan.action_slots] == [f.name for f in WALKER.action]
    db = database(WALKER)
    for slot in plan.observation_slots + plan.action_slots:
        signal = db.get_message_by_name(slot.message).get_signal_by_name(slot.signal)
        assert (signal.minimum, signal.maximum) == (slot.field.low, slot.field.high)
    # velocities (+-10) need a coarser scale than the finest: 2^-15 (20 signed bits cover +-16)
    assert {s.scale for s in plan.observation_slots if s.field.unit in ("m/s", "rad/s")} == {2.0**-15}
    assert "#define POLICY_IO_OBS_FRAMES 9u" in c_sources(WALKER)["policy_io.h"]
    env = DeckWalkerEnv()
    obs, _ = env.reset(seed=2)
    codec = Codec(WALKER)
    for a in np.random.default_rng(0).uniform(-1, 1, (20, 6)).astype(np.float32):
        _, decoded = codec.encode_observation(obs, 1)
        np.testing.assert_allclose(decoded, obs, atol=max(s.scale for s in plan.observation_slots) / 2)
        obs, _, terminated, _, _ = env.step(a)
        if terminated:
            break


def test_the_deck_preset_is_the_deck_s_ddpg_options_and_builds_them() -> None:
    from stable_baselines3.common.noise import OrnsteinUhlenbeckActionNoise

    from embedrl.train.agents import build_model, make_env
    from embedrl.train.config import DDPGConfig, preset, with_overrides
    from embedrl.train.study_agents import ClippedAdam, SeparateRatesDDPG

    cfg = preset("ddpg", "deck", "walker")
    assert isinstance(cfg, DDPGConfig)
    deck = {"actor_learning_rate": 1e-4, "learning_rate": 1e-3, "gradient_threshold": 1.0, "l2": 1e-5,
            "gamma": 0.99, "batch_size": 128, "buffer_size": 1_000_000, "tau": 1e-3, "noise_theta": 1.0,
            "noise_sigma": 0.1, "noise_dt": WALKER.sample_time_s, "reward": "deck"}  # fmt: skip
    assert {k: getattr(cfg, k) for k in deck} == deck
    cfg = with_overrides(cfg, ["net_arch=8,8", "buffer_size=1000"])
    model = build_model("ddpg", cfg, make_env(False, 0, "walker", cfg), 0, None)
    assert isinstance(model, SeparateRatesDDPG)
    for net, rate in ((model.actor, 1e-4), (model.critic, 1e-3)):
        optimizer = net.optimizer
        assert isinstance(optimizer, ClippedAdam) and optimizer.gradient_threshold == 1.0
        assert optimizer.param_groups[0]["lr"] == rate and optimizer.param_groups[0]["weight_decay"] == 1e-5
    noise = model.action_noise
    assert isinstance(noise, OrnsteinUhlenbeckActionNoise)
    assert (noise._theta, noise._dt, float(noise._sigma[0])) == (1.0, WALKER.sample_time_s, 0.1)
    model.learn(100)  # learns: both optimizers step with clipped gradients
    assert model._n_updates > 0


@pytest.mark.parametrize(
    ("algo", "name", "scenario", "said"),
    [
        ("td3", "deck", "walker", "the deck preset is DDPG's"),
        ("ddpg", "deck", "static", "--scenario walker"),
        ("ddpg", "thesis", "walker", "deck (DDPG) and tuned"),
        ("ppo", "tuned", "walker", "no walker preset for ppo"),
    ],
)
def test_presets_that_do_not_exist_are_refused(algo: str, name: str, scenario: str, said: str) -> None:
    from embedrl.train.config import preset

    with pytest.raises(ValueError, match=re.escape(said)):
        preset(algo, name, scenario)


def test_clipped_adam_scales_each_parameter_s_gradient_to_the_threshold() -> None:
    import torch

    from embedrl.train.study_agents import ClippedAdam

    big, small = torch.nn.Parameter(torch.zeros(2)), torch.nn.Parameter(torch.zeros(2))
    twin_big, twin_small = torch.nn.Parameter(torch.zeros(2)), torch.nn.Parameter(torch.zeros(2))
    clipped = ClippedAdam([big, small], lr=0.1, gradient_threshold=1.0)
    plain = torch.optim.Adam([twin_big, twin_small], lr=0.1)
    big.grad, small.grad = torch.tensor([3.0, 4.0]), torch.tensor([0.3, 0.4])  # norms 5 and 0.5
    twin_big.grad, twin_small.grad = torch.tensor([0.6, 0.8]), torch.tensor([0.3, 0.4])  # by hand: 5 -> 1
    clipped.step()
    plain.step()
    assert torch.equal(big.grad, torch.tensor([0.6, 0.8])) and torch.equal(
        small.grad, torch.tensor([0.3, 0.4])
    )
    assert torch.equal(big, twin_big) and torch.equal(small, twin_small)


def test_the_walker_s_criterion_is_the_deck_s_250_episode_window(tmp_path: Path) -> None:
    from embedrl.train.config import Budget
    from embedrl.train.monitor import CRITERIA, CURVE_FIELDS, RunMonitor

    criterion = CRITERIA["walker"]
    assert (criterion.window, criterion.threshold, criterion.save_above) == (250, 1000.0, 500.0)
    (tmp_path / "curve.csv").write_text(",".join(CURVE_FIELDS) + "\n")
    monitor = RunMonitor(tmp_path, Budget(stop="study"), {}, lambda: None, lambda: (0.0, 0.0), False,
                         criterion=criterion)  # fmt: skip
    monitor.pending_q0 = 0.0
    returns = [0.0] * 100 + [1200.0] * 300
    for i, r in enumerate(returns):
        monitor._episode(r, 1000, 1000 * (i + 1))
        if monitor.stop_now():
            break
    # 100 zeros, then 1200s: the window of 250 first averages >= 1000 with 209 of them (1200 * 209 / 250)
    assert monitor.state["criterion_episode"] == 309


def test_an_evaluation_reports_distance_and_speed_per_episode_and_falls_as_collisions() -> None:
    from embedrl.train.evaluate import evaluate

    report = evaluate(lambda obs: np.zeros(6, dtype=np.float32), 2, 7, "no torque", env_id=WALKER.env_id,
                      sample_time=WALKER.sample_time_s)  # fmt: skip
    data = report.to_json()
    assert data["collisions"] == 2 and data["sample_time_s"] == WALKER.sample_time_s
    for row, result in zip(data["per_episode"], report.results, strict=True):
        assert row["collided_with"] == FALL and row["distance"] == result.distance
        assert result.speed == pytest.approx(row["distance"] / (row["steps"] * WALKER.sample_time_s))
    assert data["mean_distance_m"] == pytest.approx(np.mean([r.distance for r in report.results]))
    assert data["min_speed_m_s"] == pytest.approx(min(r.speed or 0.0 for r in report.results))
    assert "distance mean / worst [m]" in report.table()


def test_agents_are_saved_after_episodes_at_or_above_the_threshold_and_sums_logged(tmp_path: Path) -> None:
    from embedrl.train import monitor
    from embedrl.train.monitor import EpisodeSums, SaveAboveThreshold

    class Model:
        def save(self, path: Path) -> None:
            Path(path).write_bytes(b"model")

    returns: list[float] = []
    saver = SaveAboveThreshold(500.0, tmp_path / "saved", lambda: returns)
    sums = EpisodeSums(tmp_path / "sums.csv", ("episode_forward", "distance"))
    saver.model = sums.model = Model()  # type: ignore[assignment]
    for i, ret in enumerate([499.0, 500.0, 10.0, 800.0]):
        returns.append(ret)
        info = {"episode": {"r": ret, "episode_forward": ret, "distance": i / 10}}
        for callback in (saver, sums):
            callback.locals = {"dones": [True], "infos": [info]}
            callback.num_timesteps = 100 * (i + 1)
            callback._on_step()
    assert sorted(p.name for p in (tmp_path / "saved").iterdir()) == ["episode2.zip", "episode4.zip"]
    rows = (tmp_path / "sums.csv").read_text().splitlines()
    assert rows[0] == "steps,episode_forward,distance" and rows[2] == "200,500.000000,0.100000"
    assert monitor.MAX_SAVED_AGENTS == 50


def test_an_evaluation_times_walker_episodes_with_the_walkers_sample_time() -> None:
    from embedrl.train.evaluate import evaluate

    report = evaluate(lambda obs: np.zeros(6, dtype=np.float32), 2, 0, "no torque", env_id=WALKER.env_id)
    for r in report.results:  # without torque it falls: a short episode, timed at 8 ms a step
        assert r.outcome == "collision" and r.time_s == pytest.approx(r.steps * WALKER.sample_time_s)
        assert r.distance is not None
        assert r.speed == pytest.approx(r.distance / (r.steps * WALKER.sample_time_s))
