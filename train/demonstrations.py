"""Demonstrations of the potential-field controller before training: transitions seeded into an
off-policy agent's replay buffer, or behaviour cloning of PPO's actor (whole episodes for a recurrent one)."""

from __future__ import annotations

import itertools
from collections.abc import Iterator
from typing import Any

import gymnasium as gym
import numpy as np
import torch
from sb3_contrib import RecurrentPPO
from stable_baselines3 import PPO
from stable_baselines3.common.off_policy_algorithm import OffPolicyAlgorithm
from stable_baselines3.common.vec_env import VecEnv, VecNormalize

from embedrl.common import DEMONSTRATION_SEED
from embedrl.train.agents import env_kwargs, make_env
from embedrl.train.config import (
    PPOConfig,
)
from embedrl.train.scenarios import DEFAULT_SCENARIO, SCENARIOS, TEACHERS


def _demonstration_steps(
    episodes: int, noise: float, seed: int, scenario: str, cfg: Any
) -> Iterator[
    tuple[np.ndarray, np.ndarray, np.ndarray, np.ndarray, np.ndarray, np.ndarray, list[dict[str, Any]]]
]:
    """The scenario's potential-field controller with Gaussian noise on its actions, ``episodes`` episodes,
    as vector-env steps ``(obs, clean actions, actions, next obs, rewards, dones, infos)``: one row per
    robot, ``next obs`` the terminal observation where a row is done.

    One env per scenario with one robot, reset with seed ``DEMONSTRATION_SEED + 1000 * seed + episode``;
    for several robots, the training vector env itself (absorbing rows included), seeded once."""
    from embedrl.train.potential_field import PotentialFieldController

    teacher = TEACHERS.get(scenario)  # the controller sees the full observation, the learner its own
    controller = PotentialFieldController(scenario=teacher or scenario)
    rng = np.random.default_rng(seed)
    first = DEMONSTRATION_SEED + 1000 * seed
    if SCENARIOS[scenario].robots > 1:
        venv = make_env(False, first, scenario, cfg)
        obs = np.asarray(venv.reset())
        finished = 0
        while finished < episodes:
            clean = np.stack([controller(o) for o in obs])
            actions = np.clip(clean + rng.normal(0.0, noise, clean.shape), -1.0, 1.0).astype(np.float32)
            stepped, rewards, dones, infos = venv.step(actions)
            next_obs = np.asarray(stepped)
            stored = next_obs.copy()
            for i in np.flatnonzero(dones):
                stored[i] = infos[i]["terminal_observation"]
            yield obs, clean, actions, stored, rewards, dones, infos
            obs = next_obs
            finished += bool(np.all(dones))  # the episode is over when every row is done
        venv.close()
        return
    env = gym.make(SCENARIOS[scenario].env_id, **env_kwargs(cfg))
    for episode in range(episodes):
        o, _ = env.reset(seed=first + episode)
        done = False
        while not done:
            c = controller(env.unwrapped.full_observation() if teacher else o)  # type: ignore[attr-defined]
            action = np.clip(c + rng.normal(0.0, noise, 2), -1.0, 1.0).astype(np.float32)
            next_o, reward, terminated, truncated, _ = env.step(action)
            done = terminated or truncated
            info = {"TimeLimit.truncated": truncated and not terminated}
            yield o[None], c[None], action[None], next_o[None], np.array([reward]), np.array([done]), [info]
            o = next_o
    env.close()


def seed_replay_buffer(
    model: OffPolicyAlgorithm,
    episodes: int,
    noise: float,
    seed: int,
    scenario: str = DEFAULT_SCENARIO,
    cfg: Any = None,
) -> int:
    """Put the scenario's potential-field episodes (noisy actions) into the replay buffer; return the
    transitions added."""
    assert model.replay_buffer is not None
    added = 0
    for obs, _, actions, next_obs, rewards, dones, infos in _demonstration_steps(
        episodes, noise, seed, scenario, cfg
    ):
        model.replay_buffer.add(obs, next_obs, actions, rewards, dones, infos)
        added += len(obs)
    return added


def controller_demonstrations(
    episodes: int, noise: float, seed: int, scenario: str = DEFAULT_SCENARIO, cfg: Any = None
) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """Observations visited with noisy potential-field actions, labelled with its clean actions, and
    whether each starts an episode."""
    observations: list[np.ndarray] = []
    labels: list[np.ndarray] = []
    starts: list[bool] = []
    start = True
    for obs, clean, _, _, _, dones, _ in _demonstration_steps(episodes, noise, seed, scenario, cfg):
        live = np.any(obs != 0.0, axis=1)  # not the absorbing rows of robots already through
        observations.extend(obs[live])
        labels.extend(clean[live])
        starts.extend([start] * int(live.sum()))
        start = bool(np.all(dones))
    return (
        np.array(observations, dtype=np.float32),
        np.array(labels, dtype=np.float32),
        np.array(starts, dtype=bool),
    )


def warm_start(
    model: PPO | RecurrentPPO,
    env: VecEnv,
    episodes: int,
    epochs: int,
    seed: int,
    scenario: str = DEFAULT_SCENARIO,
    cfg: Any = None,
) -> float:
    """Behaviour-clone the potential-field controller into PPO's policy mean; return the final loss."""
    obs, labels, starts = controller_demonstrations(episodes, 0.2, seed, scenario, cfg)
    if isinstance(env, VecNormalize):
        rms: Any = env.obs_rms
        rms.mean, rms.var, rms.count = (
            obs.mean(0).astype(np.float64),
            obs.var(0).astype(np.float64),
            float(len(obs)),
        )
        obs = np.asarray(env.normalize_obs(obs), dtype=np.float32)
    x, y = torch.as_tensor(obs), torch.as_tensor(labels)
    policy: Any = model.policy
    optimizer = torch.optim.Adam(policy.parameters(), lr=1e-3)
    generator = torch.Generator().manual_seed(seed)
    loss = torch.zeros(())
    if isinstance(model, RecurrentPPO):
        return _clone_sequences(policy, optimizer, x, y, starts, epochs, generator)
    for _ in range(epochs):
        order = torch.randperm(len(x), generator=generator)
        for start in range(0, len(x), 256):
            idx = order[start : start + 256]
            mean = policy.get_distribution(x[idx]).distribution.mean
            loss = torch.nn.functional.mse_loss(mean, y[idx])
            optimizer.zero_grad()
            loss.backward()  # type: ignore[no-untyped-call]
            optimizer.step()
    return float(loss.detach())


SEQUENCES_PER_BATCH = 16
"""Demonstration episodes per gradient step when cloning into an LSTM policy."""


def _clone_sequences(
    policy: Any,
    optimizer: torch.optim.Optimizer,
    x: torch.Tensor,
    y: torch.Tensor,
    starts: np.ndarray,
    epochs: int,
    generator: torch.Generator,
) -> float:
    """Behaviour cloning into a recurrent policy: each demonstration episode a sequence from zero state,
    padded to the longest, the loss over real steps only; return the final loss."""
    bounds = [*np.flatnonzero(starts), len(starts)]
    episodes = [(a, b) for a, b in itertools.pairwise(bounds)]
    length = max(b - a for a, b in episodes)
    lstm = policy.lstm_actor
    loss = torch.zeros(())
    for _ in range(epochs):
        order = torch.randperm(len(episodes), generator=generator).tolist()
        for first in range(0, len(order), SEQUENCES_PER_BATCH):
            chosen = [episodes[i] for i in order[first : first + SEQUENCES_PER_BATCH]]
            seq = torch.zeros(length, len(chosen), x.shape[1])
            target = torch.zeros(length, len(chosen), y.shape[1])
            mask = torch.zeros(length, len(chosen), 1)
            for k, (a, b) in enumerate(chosen):
                seq[: b - a, k], target[: b - a, k], mask[: b - a, k] = x[a:b], y[a:b], 1.0
            features = policy.extract_features(seq.reshape(-1, x.shape[1]), policy.pi_features_extractor)
            out, _ = lstm(features.reshape(length, len(chosen), -1))  # zero state: each an episode start
            latent = policy.mlp_extractor.forward_actor(out.reshape(length * len(chosen), -1))
            mean = policy.action_net(latent).reshape(length, len(chosen), -1)
            loss = ((mean - target) ** 2 * mask).sum() / (mask.sum() * y.shape[1])
            optimizer.zero_grad()
            loss.backward()
            optimizer.step()
    return float(loss.detach())


def demonstration_episodes(cfg: Any) -> int:
    """Episodes of the potential-field controller the agent learnt from before training (not in the curve)."""
    return int(cfg.warm_start_demonstrations if isinstance(cfg, PPOConfig) else cfg.demonstrations)
