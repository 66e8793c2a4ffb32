"""The study's agent structure (train/study_agents.py) and the ``thesis`` preset that uses it."""

from __future__ import annotations

from dataclasses import replace
from pathlib import Path
from typing import Any

import numpy as np
import pytest
import torch as th
from torch.nn import functional as F

from embedrl.train.agents import CLASSES, build_model, make_env
from embedrl.train.config import DDPGConfig, PPOConfig, SACConfig, TD3Config, preset

OBS = np.random.default_rng(0).uniform(-1, 1, (32, 6)).astype(np.float32)


def _model(algo: str, **changes: Any) -> Any:
    cfg: Any = replace(preset(algo, "thesis"), net_arch=(16, 8), **changes)
    if isinstance(cfg, PPOConfig):
        cfg = replace(cfg, n_steps=64, batch_size=32, n_epochs=2)
    return build_model(algo, cfg, make_env(isinstance(cfg, PPOConfig), 0, "static", cfg), 0, None)


def test_the_thesis_preset_is_the_studys_setup() -> None:
    ddpg, td3, sac, ppo = (preset(a, "thesis") for a in ("ddpg", "td3", "sac", "ppo"))
    assert isinstance(ddpg, DDPGConfig) and isinstance(td3, TD3Config)
    assert isinstance(sac, SACConfig) and isinstance(ppo, PPOConfig)
    assert (ddpg.actor_learning_rate, ddpg.learning_rate) == (1e-4, 1e-3)
    assert ppo.n_steps == 512
    for cfg in (ddpg, td3, sac):
        assert cfg.learning_starts == 0 and cfg.demonstrations == 0 and cfg.two_branch_critic
        assert (cfg.batch_size, cfg.buffer_size, cfg.gamma) == (128, 1_000_000, 0.99)
    assert sac.softplus_std and ppo.softplus_std and ppo.warm_start_demonstrations == 0
    # tuned keeps SB3's structure (the shipped policies' structure).
    assert not preset("td3", "tuned").two_branch_critic  # type: ignore[union-attr]
    assert not preset("ppo", "tuned").softplus_std  # type: ignore[union-attr]


@pytest.mark.training
def test_two_branch_critic_adds_an_observation_and_an_action_branch() -> None:
    model = _model("td3")
    critic = model.critic
    assert type(critic).__name__ == "TwoBranchCritic" and len(critic.q_networks) == 2
    q = critic.q_networks[0]
    assert q.obs_path[0].in_features == 6 and q.action_path.in_features == 2  # not joined at the input
    obs, act = th.as_tensor(OBS), th.as_tensor(np.tanh(OBS[:, :2]))
    l1, l2 = q.obs_path[0], q.obs_path[2]
    by_hand = q.out(F.relu(l2(F.relu(l1(obs))) + q.action_path(act)))
    assert th.allclose(critic(obs, act)[0], by_hand)
    assert th.allclose(critic.q1_forward(obs, act), by_hand)
    # Trained: the critic's parameters change and stay finite.
    before = [p.detach().clone() for p in critic.parameters()]
    model.learn(300)
    after = list(critic.parameters())
    assert all(th.isfinite(p).all() for p in after)
    assert any(not th.equal(a, b) for a, b in zip(after, before, strict=True))


def test_sac_standard_deviation_is_softplus_of_a_linear_head() -> None:
    actor = _model("sac").actor
    obs = th.as_tensor(OBS)
    mean, log_std, _ = actor.get_action_dist_params(obs)
    latent = actor.latent_pi(obs)
    assert th.allclose(log_std.exp(), F.softplus(actor.std(latent)), rtol=1e-5)
    assert th.allclose(mean, actor.mu(latent))
    assert not hasattr(actor, "log_std")
    # The deterministic action is tanh(mean), as in SB3's SAC.
    assert th.allclose(actor(obs, deterministic=True), th.tanh(mean))


@pytest.mark.training
def test_ppo_standard_deviation_is_softplus_of_a_state_dependent_head() -> None:
    model = _model("ppo", log_std_init=np.log(0.5))
    policy = model.policy
    obs = th.as_tensor(OBS)
    std = policy.get_distribution(obs).distribution.stddev
    assert th.allclose(std, th.full_like(std, 0.5), atol=0.02)  # exp(log_std_init) at the start
    assert {id(p) for p in policy.std_net.parameters()} <= {
        id(p) for group in policy.optimizer.param_groups for p in group["params"]
    }
    model.learn(128)
    assert model._n_updates > 0
    std = policy.get_distribution(obs).distribution.stddev
    latent = policy.mlp_extractor.forward_actor(obs)
    assert th.allclose(std, F.softplus(policy.std_net(latent)), rtol=1e-5)
    assert std.std(dim=0).max() > 0  # differs between states


@pytest.mark.training
def test_ddpg_actor_and_critic_learn_at_their_own_rates(tmp_path: Path) -> None:
    model = _model("ddpg")
    model.learn(200)
    assert [g["lr"] for g in model.actor.optimizer.param_groups] == [1e-4]
    assert [g["lr"] for g in model.critic.optimizer.param_groups] == [1e-3]
    model.save(tmp_path / "ddpg.zip")
    loaded = CLASSES["ddpg"].load(tmp_path / "ddpg.zip", device="cpu")
    assert loaded.actor_learning_rate == 1e-4  # type: ignore[attr-defined]
    loaded.set_env(model.get_env())
    loaded.learn(130, reset_num_timesteps=False)
    assert [g["lr"] for g in loaded.actor.optimizer.param_groups] == [1e-4]  # type: ignore[attr-defined]
    assert [g["lr"] for g in loaded.critic.optimizer.param_groups] == [1e-3]  # type: ignore[attr-defined]


@pytest.mark.training
@pytest.mark.parametrize("algo", ["ddpg", "td3", "sac", "ppo"])
def test_thesis_models_load_safely_and_export_to_the_same_actions(algo: str, tmp_path: Path) -> None:
    """The safe loader accepts embedrl's classes by name; the ONNX actor gives predict()'s actions."""
    import onnxruntime as ort

    from embedrl.export.sb3_onnx import build_onnx
    from embedrl.train.models import load_sb3, save_normalization

    model = _model(algo)
    model.learn(150)
    model.save(tmp_path / "m.zip")
    if algo == "ppo":
        save_normalization(model.get_env(), tmp_path / "vecnormalize.npz")
    loaded = load_sb3(tmp_path / "m.zip")
    assert type(loaded.policy) is type(model.policy)
    graph = build_onnx(loaded, "test")
    session = ort.InferenceSession(graph.SerializeToString())
    name = session.get_inputs()[0].name
    actions = session.run(None, {name: OBS})[0]
    np.testing.assert_allclose(actions, loaded.predict(OBS), atol=1e-5)
