"""A run's training env and its SB3 agent: one Monitor-ed env or one slot per robot, the algorithm's
class with the preset's hyperparameters, noise and network."""

from __future__ import annotations

from pathlib import Path
from typing import Any

import gymnasium as gym
import numpy as np
import torch
from sb3_contrib import RecurrentPPO
from stable_baselines3 import PPO, SAC, TD3
from stable_baselines3.common.base_class import BaseAlgorithm
from stable_baselines3.common.monitor import Monitor
from stable_baselines3.common.noise import NormalActionNoise, OrnsteinUhlenbeckActionNoise
from stable_baselines3.common.vec_env import DummyVecEnv, VecEnv, VecNormalize

from embedrl.train.config import (
    DDPGConfig,
    PPOConfig,
    RecurrentPPOConfig,
    SACConfig,
    TD3Config,
)
from embedrl.train.deck_reward import VARIANTS
from embedrl.train.rewards import SHAPING_GAIN, SUCCESS_BONUS
from embedrl.train.scenarios import DEFAULT_SCENARIO, SCENARIOS, team_env
from embedrl.train.study_agents import (
    SeparateRatesDDPG,
    SoftplusActorCriticPolicy,
    StudySACPolicy,
    StudyTD3Policy,
)

CLASSES: dict[str, type[BaseAlgorithm]] = {
    "ddpg": SeparateRatesDDPG,
    "td3": TD3,
    "sac": SAC,
    "ppo": PPO,
    "recurrent-ppo": RecurrentPPO,
}


def make_env(normalize: bool, seed: int, scenario: str = DEFAULT_SCENARIO, cfg: Any = None) -> VecEnv:
    """The training env of a scenario: one Monitor-ed env, or for a scenario with several robots one slot
    per robot of its team env."""
    kwargs = env_kwargs(cfg)
    env: VecEnv
    spec = SCENARIOS[scenario]
    if spec.robots > 1:
        from embedrl.train.shared_policy import SharedPolicyVecEnv

        env = SharedPolicyVecEnv(team_env(spec, **kwargs))
    else:
        env_id = spec.env_id

        def monitored() -> gym.Env[Any, Any]:
            inner = gym.make(env_id, **kwargs)  # an env's per-episode sums (the walker's reward terms) logged
            return Monitor(inner, info_keywords=tuple(getattr(inner.unwrapped, "EPISODE_KEYS", ())))

        env = DummyVecEnv([monitored])
    env.seed(seed)
    if normalize:
        env = VecNormalize(env, norm_obs=True, norm_reward=False)
    return env


def env_kwargs(cfg: Any) -> dict[str, Any]:
    """The env arguments a run's hyperparameters set (the reward, and the success bonus where it is not
    the default, so envs without that argument keep working; the walker's reward, one of the deck's stages,
    whose names differ from the warehouse rewards')."""
    if cfg is not None and cfg.reward in VARIANTS:
        return {"reward": cfg.reward}
    if cfg is None or (cfg.reward == "thesis" and cfg.success_bonus == SUCCESS_BONUS):
        return {}
    out: dict[str, Any] = {"reward": cfg.reward}
    if cfg.success_bonus != SUCCESS_BONUS:
        out["success_bonus"] = cfg.success_bonus
    if cfg.reward == "shaped":  # shaping leaves the optimal policy unchanged only at the agent's own discount
        out["shaping_gamma"] = cfg.gamma
        if cfg.shaping_gain != SHAPING_GAIN:
            out["shaping_gain"] = cfg.shaping_gain
    return out


def model_class(algo: str, cfg: Any) -> type[BaseAlgorithm]:
    """The class a run's checkpoints load with: the algorithm's, or sbx's TD3 for the jax backend."""
    if getattr(cfg, "backend", "torch") == "jax":
        from embedrl.train.jax_agents import jax_td3_class

        return jax_td3_class()  # type: ignore[no-any-return]
    return CLASSES[algo]


def build_model(algo: str, cfg: Any, env: VecEnv, seed: int, tb: Path | None) -> BaseAlgorithm:
    """A fresh SB3 model; a new policy_kwargs dict every time (SB3 writes into it)."""
    common: dict[str, Any] = {
        "seed": seed,
        "device": "cpu",
        "verbose": 0,
        "gamma": cfg.gamma,
        "learning_rate": cfg.learning_rate,
        "tensorboard_log": str(tb) if tb else None,
    }
    if isinstance(cfg, PPOConfig):
        kwargs = {
            "net_arch": {"pi": list(cfg.net_arch), "vf": list(cfg.net_arch)},
            "activation_fn": torch.nn.ReLU,
            "log_std_init": cfg.log_std_init,
        }
        algorithm: Any = PPO
        policy: Any = SoftplusActorCriticPolicy if cfg.softplus_std else "MlpPolicy"
        if isinstance(cfg, RecurrentPPOConfig):
            kwargs.update(lstm_hidden_size=cfg.lstm_hidden_size, n_lstm_layers=cfg.n_lstm_layers)
            algorithm, policy = RecurrentPPO, "MlpLstmPolicy"
        return algorithm(  # type: ignore[no-any-return]
            policy,
            env,
            n_steps=cfg.n_steps,
            batch_size=cfg.batch_size,
            n_epochs=cfg.n_epochs,
            gae_lambda=cfg.gae_lambda,
            clip_range=cfg.clip_range,
            ent_coef=cfg.ent_coef,
            policy_kwargs=kwargs,
            **common,
        )
    policy_kwargs: dict[str, Any] = {"net_arch": list(cfg.net_arch), "activation_fn": torch.nn.ReLU}
    off = {
        "batch_size": cfg.batch_size,
        "buffer_size": cfg.buffer_size,
        "tau": cfg.tau,
        "learning_starts": cfg.learning_starts,
        "train_freq": cfg.train_freq,
        "gradient_steps": cfg.gradient_steps,
        "policy_kwargs": policy_kwargs,
    }
    return _off_policy(cfg, env, common, off, policy_kwargs)


def _off_policy(
    cfg: Any, env: VecEnv, common: dict[str, Any], off: dict[str, Any], policy_kwargs: dict[str, Any]
) -> BaseAlgorithm:
    """DDPG, TD3 (SB3's, or sbx's on JAX) or SAC with their noise and the study's structures."""
    n = env.action_space.shape[0]  # type: ignore[index]
    seed, tb = common["seed"], common["tensorboard_log"]
    # The study's structures need embedrl's classes; without them models stay plain SB3 files.
    deterministic_policy: Any = "MlpPolicy"
    if cfg.two_branch_critic and not isinstance(cfg, SACConfig):
        deterministic_policy = StudyTD3Policy
        policy_kwargs["two_branch_critic"] = True
    if isinstance(cfg, DDPGConfig):
        ou = OrnsteinUhlenbeckActionNoise(
            np.zeros(n), cfg.noise_sigma * np.ones(n), theta=cfg.noise_theta, dt=cfg.noise_dt
        )
        return SeparateRatesDDPG(
            deterministic_policy,
            env,
            action_noise=ou,
            actor_learning_rate=cfg.actor_learning_rate,
            gradient_threshold=cfg.gradient_threshold,
            l2=cfg.l2,
            **off,
            **common,
        )
    if isinstance(cfg, TD3Config):
        noise = NormalActionNoise(np.zeros(n), cfg.noise_sigma * np.ones(n))
        if cfg.backend == "jax":
            if cfg.two_branch_critic:
                raise ValueError(
                    "the jax backend trains SB3's standard critic: --set two_branch_critic=false"
                )
            from embedrl.train.jax_agents import build_jax_td3

            return build_jax_td3(cfg, env, seed, Path(tb) if tb else None, noise)  # type: ignore[no-any-return]
        return TD3(
            deterministic_policy,
            env,
            action_noise=noise,
            policy_delay=cfg.policy_delay,
            target_policy_noise=cfg.target_policy_noise,
            **off,
            **common,
        )
    assert isinstance(cfg, SACConfig)
    sac_policy: Any = "MlpPolicy"
    if cfg.softplus_std or cfg.two_branch_critic:
        sac_policy = StudySACPolicy
        policy_kwargs.update(softplus_std=cfg.softplus_std, two_branch_critic=cfg.two_branch_critic)
    return SAC(sac_policy, env, ent_coef=cfg.ent_coef, **off, **common)
