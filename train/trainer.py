"""Training runs: SB3 agents on the warehouse env, the study's stop criterion, checkpoints and resume.

A run directory is self-describing::

    config.json        algorithm, preset, seed, hyperparameters, budget, package versions
    curve.csv          one row per training episode: steps, return, 50-episode average, the critic's Q0
    summary.json       criterion reached?, episodes and env steps to it, first deterministic success, time
    progress.png       MATLAB-style: episode return, 50-episode average, Episode Q0
    successes.png      successes over training, per robot, and the validation evaluations
    evaluations.csv    one row per validation evaluation: steps, success rate, mean return
    best_model.zip     the checkpoint with the best validation evaluation; last_model.zip the last one
    model.zip          the selected policy: best_model.zip (or last_model.zip without validations), plus
                       vecnormalize.npz and .pkl when observations are normalised
    checkpoint/        the last checkpoint: model, replay buffer, the training env itself (mid-episode),
                       every random generator's state and the counters (written as checkpoint.partial,
                       then swapped in: a complete checkpoint exists at every moment)
    tb/                TensorBoard logs

Checkpoints are taken where SB3 starts collecting experience (after a training update), so a resumed run
continues exactly where the checkpoint left it: the same env state, the same random draws, the same
updates. Killed and resumed, a run ends bit-identical to the same run uninterrupted.
"""

from __future__ import annotations

import csv
import itertools
import json
import os
import pickle
import random
import shutil
import time
from collections.abc import Callable, Iterator, Sequence
from dataclasses import dataclass
from pathlib import Path
from typing import Any

import gymnasium as gym
import numpy as np
import torch
from sb3_contrib import RecurrentPPO
from stable_baselines3 import PPO, SAC, TD3
from stable_baselines3.common.base_class import BaseAlgorithm
from stable_baselines3.common.callbacks import BaseCallback, CallbackList
from stable_baselines3.common.monitor import Monitor
from stable_baselines3.common.noise import NormalActionNoise, OrnsteinUhlenbeckActionNoise
from stable_baselines3.common.off_policy_algorithm import OffPolicyAlgorithm
from stable_baselines3.common.vec_env import DummyVecEnv, VecEnv, VecNormalize
from tqdm import tqdm

from embedrl.common import DEMONSTRATION_SEED, VALIDATION_SEED, atomic_write, provenance, read_json
from embedrl.train import deck_reward
from embedrl.train.config import (
    ALGOS,
    Budget,
    DDPGConfig,
    PPOConfig,
    RecurrentPPOConfig,
    RunConfig,
    SACConfig,
    TD3Config,
    preset,
    to_dict,
    untrained_budget,
    warmup_steps,
    with_overrides,
)
from embedrl.train.deck_reward import VARIANTS
from embedrl.train.errors import UsageError
from embedrl.train.evaluate import evaluate
from embedrl.train.models import normalization_of, save_normalization, stamp_model
from embedrl.train.portable import machine
from embedrl.train.rewards import SHAPING_GAIN, SUCCESS_BONUS, check_options
from embedrl.train.scenarios import DEFAULT_SCENARIO, SCENARIOS, TEACHERS, WALKER, team_env
from embedrl.train.study_agents import (
    SeparateRatesDDPG,
    SoftplusActorCriticPolicy,
    StudySACPolicy,
    StudyTD3Policy,
)

BEST_MODEL = "best_model"
"""The checkpoint with the best validation evaluation so far (``best_model.zip``)."""
WARM_START_MODEL = "warm_start_model"
"""PPO's behaviour-cloned start before any PPO update (``warm_start_model.zip``): what cloning alone gives."""
LAST_MODEL = "last_model"
"""The model when training ended (``last_model.zip``)."""
STOP_WINDOW = 50
"""The study's stop criterion: mean return of the last 50 training episodes..."""
STOP_THRESHOLD = 2.0
"""... at least 2 (MATLAB's AverageReward)."""


@dataclass(frozen=True)
class Criterion:
    """A scenario's training criteria on the training episodes' returns (MATLAB's training options)."""

    window: int = STOP_WINDOW
    """Episodes averaged (``ScoreAveragingWindowLength``)."""
    threshold: float = STOP_THRESHOLD
    """The stop criterion: the window's mean return reaches this (``StopTrainingValue``, AverageReward)."""
    save_above: float | None = None
    """Agents of episodes whose return reaches this are saved (``SaveAgentValue``, EpisodeReward)."""


WALKER_TARGET_SPEED = 1.0
"""The walker's target: 1 m/s, the deck's walking speed [m/s]."""
CRITERIA = {
    WALKER.name: Criterion(
        window=250,
        threshold=WALKER_TARGET_SPEED * WALKER.max_steps,
        save_above=0.5 * WALKER_TARGET_SPEED * WALKER.max_steps,
    )
}
"""The scenarios whose criteria are not the study's (:class:`Criterion`'s defaults). The walker's: the deck's
250-episode window; a return of ``v * 1000`` is the forward term of a whole episode at mean speed ``v``, so
the stop value is the target speed kept for a whole episode (its survive bonus, 25, about pays for the
effort and height terms), and agents are saved from half of it on."""
SAVED_AGENTS = "saved_agents"
"""The folder of a run's agents saved above the save threshold (``episode<N>.zip``)."""
MAX_SAVED_AGENTS = 50
"""At most this many agents are saved above the threshold (the first ones: MATLAB saves each, without end)."""
CLASSES: dict[str, type[BaseAlgorithm]] = {
    "ddpg": SeparateRatesDDPG,
    "td3": TD3,
    "sac": SAC,
    "ppo": PPO,
    "recurrent-ppo": RecurrentPPO,
}
EVALUATIONS_FILE = "evaluations.csv"
EVALUATION_FIELDS = ("steps", "success_rate", "mean_return")
"""evaluations.csv: one row per validation evaluation."""
CURVE_FIELDS = ("episode", "steps", "return", "length", "average50", "q0", "success", "robot")
"""curve.csv's columns; ``robot`` is the robot's index (two robots share one policy and one curve)."""
CHECKPOINT_FILES = ("model.zip", "env.pkl", "random.pkl", "state.json")
"""What every checkpoint holds (plus replay_buffer.pkl for DDPG, TD3 and SAC); state.json is written last."""


def make_env(normalize: bool, seed: int, scenario: str = DEFAULT_SCENARIO, cfg: Any = None) -> VecEnv:
    """The training env of a scenario: one Monitor-ed env, or one slot per robot for two robots."""
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
    n = env.action_space.shape[0]  # type: ignore[index]
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


def _demonstration_steps(
    episodes: int, noise: float, seed: int, scenario: str, cfg: Any
) -> Iterator[
    tuple[np.ndarray, np.ndarray, np.ndarray, np.ndarray, np.ndarray, np.ndarray, list[dict[str, Any]]]
]:
    """The scenario's potential-field controller with Gaussian noise on its actions, ``episodes`` episodes,
    as vector-env steps ``(obs, clean actions, actions, next obs, rewards, dones, infos)``: one row per
    robot, ``next obs`` the terminal observation where a row is done.

    One env per scenario with one robot, reset with seed ``DEMONSTRATION_SEED + 1000 * seed + episode``;
    for two robots, the training vector env itself (absorbing rows included), seeded once."""
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


def _demonstrations(
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
    obs, labels, starts = _demonstrations(episodes, 0.2, seed, scenario, cfg)
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


def q0(model: BaseAlgorithm, obs: np.ndarray) -> float:
    """The critic's estimate of a state's value (MATLAB's Episode Q0)."""
    with torch.no_grad():
        x = torch.as_tensor(np.asarray(obs, dtype=np.float32).reshape(1, -1))
        policy: Any = model.policy
        if isinstance(model, RecurrentPPO):  # an episode's first state: zero LSTM state
            zero = torch.zeros(policy.lstm_hidden_state_shape[0], 1, policy.lstm_hidden_state_shape[2])
            return float(policy.predict_values(x, (zero, zero), torch.ones(1))[0, 0])
        if isinstance(model, PPO):
            return float(policy.predict_values(x)[0, 0])
        action = policy.actor(x, deterministic=True) if isinstance(model, SAC) else policy.actor(x)
        return float(min(q[0, 0] for q in policy.critic(x, action)))


def stop_rule_fired(rule: str, state: dict[str, Any]) -> int | None:
    """The step at which stop rule ``rule`` fired in a run's ``state`` (None: it has not)."""
    key = {"study": "criterion_step", "validation": "target_step"}.get(rule)
    return None if key is None else state.get(key)


class SaveAboveThreshold(BaseCallback):
    """Saves the agent after each training episode whose return reaches ``threshold`` (MATLAB's
    ``SaveAgentCriteria`` EpisodeReward) as ``folder/episode<N>.zip``, at most :data:`MAX_SAVED_AGENTS`;
    ``returns`` is the run's episode log (its length numbers the episodes)."""

    def __init__(self, threshold: float, folder: Path, returns: Callable[[], list[float]]) -> None:
        super().__init__()
        self.threshold, self.folder, self.returns = threshold, folder, returns

    def _on_step(self) -> bool:
        for done, info in zip(self.locals["dones"], self.locals["infos"], strict=True):
            returns = self.returns()
            if done and "episode" in info and returns and returns[-1] >= self.threshold:
                saved = list(self.folder.glob("episode*.zip")) if self.folder.is_dir() else []
                if len(saved) < MAX_SAVED_AGENTS:
                    self.folder.mkdir(exist_ok=True)
                    self.model.save(self.folder / f"episode{len(returns)}.zip")
        return True


class EpisodeSums(BaseCallback):
    """Appends what ``Monitor`` recorded of an env's ``EPISODE_KEYS`` (the walker's reward terms summed per
    episode, the distance walked) to ``path``, one row per training episode."""

    def __init__(self, path: Path, keys: Sequence[str]) -> None:
        super().__init__()
        self.path, self.keys = path, tuple(keys)

    def _on_step(self) -> bool:
        for done, info in zip(self.locals["dones"], self.locals["infos"], strict=True):
            if done and "episode" in info:
                new = not self.path.exists()
                with self.path.open("a", newline="") as f:
                    writer = csv.writer(f)
                    if new:
                        writer.writerow(("steps", *self.keys))
                    values = (f"{float(info['episode'][k]):.6f}" for k in self.keys)
                    writer.writerow((self.num_timesteps, *values))
        return True


class RunMonitor(BaseCallback):
    """Episode log, stop criterion, deterministic evaluations, checkpoints and the progress bar."""

    def __init__(
        self,
        run: Path,
        budget: Budget,
        state: dict[str, Any],
        save: Callable[[], None],
        validate: Callable[[], tuple[float, float]],
        progress: bool,
        save_best: Callable[[], None] = lambda: None,
        trained: Callable[[], bool] = lambda: True,
        criterion: Criterion | None = None,
    ) -> None:
        super().__init__()
        self.run, self.budget, self.state = run, budget, state
        self.criterion = criterion or Criterion()
        self.save, self.validate, self.save_best = save, validate, save_best
        self.trained = trained
        self.returns: list[float] = list(state.get("returns", []))
        self.pending_q0: float | None = None
        self.bar = tqdm(
            total=budget.max_steps,
            initial=state.get("steps", 0),
            unit="step",
            disable=not progress,
            desc="train",
        )
        self.next_checkpoint = state.get("next_checkpoint", budget.checkpoint_every)
        self.next_eval = state.get("next_eval", budget.eval_every)
        self.checkpoint_due = False
        if "pending_q0" in state:
            self.pending_q0 = state["pending_q0"]

    def _on_training_start(self) -> None:
        if self.pending_q0 is None:
            self.pending_q0 = q0(self.model, self.model._last_obs[0])  # type: ignore[index]

    def _on_rollout_start(self) -> None:
        # Here SB3 has applied every update for the steps so far and holds no unused experience: the
        # one place where model, buffers and env together are a state a resumed run can continue from.
        if self.checkpoint_due:
            self.checkpoint_due = False
            self.checkpoint()

    def checkpoint(self) -> None:
        self.state.update(
            # a resume with nothing left to train never stepped: its steps are the checkpoint's own
            steps=self.num_timesteps or int(self.state.get("steps", 0)),
            returns=self.returns,
            next_checkpoint=self.next_checkpoint,
            next_eval=self.next_eval,
            pending_q0=self.pending_q0,
        )
        self.save()

    def _on_step(self) -> bool:
        steps = self.num_timesteps
        self.bar.update(steps - self.bar.n)
        for robot, (done, info, obs) in enumerate(
            zip(self.locals["dones"], self.locals["infos"], self.locals["new_obs"], strict=True)
        ):
            if done and "episode" in info:
                episode = info["episode"]
                success = bool(info.get("is_success"))
                # The study's return (without a shaping term) is what its criterion averages.
                ret = float(info.get("study_return", episode["r"]))
                self._episode(ret, int(episode["l"]), steps, success, robot)
                self.pending_q0 = q0(self.model, obs)
        if steps >= self.next_eval:
            self.next_eval += self.budget.eval_every
            self.evaluation(steps)
        if steps >= self.next_checkpoint:
            self.next_checkpoint += self.budget.checkpoint_every
            self.checkpoint_due = True  # taken when SB3 next starts collecting
        return not self.stop_now() and len(self.returns) < self.budget.max_episodes

    def stop_now(self) -> bool:
        """Whether the run's stop rule has fired."""
        return stop_rule_fired(self.budget.stop, self.state) is not None

    def evaluation(self, steps: int) -> None:
        """A validation evaluation: logged, the best one kept, the deployable criterion recorded. An
        untrained policy (evaluated within the random warm-up) is kept as the best only until a trained
        one is evaluated: crashing at once scores better than wandering, and a fresh actor often does."""
        success, mean_return = self.validate()
        self.state["evaluations"] = self.state.get("evaluations", 0) + 1
        new_file = not (self.run / EVALUATIONS_FILE).exists()
        with (self.run / EVALUATIONS_FILE).open("a", newline="") as f:
            writer = csv.writer(f)
            if new_file:
                writer.writerow(EVALUATION_FIELDS)
            writer.writerow([steps, f"{success:.6f}", f"{mean_return:.6f}"])
        threshold = self.criterion.threshold
        if self.state.get("first_deterministic_criterion_step") is None and mean_return >= threshold:
            self.state["first_deterministic_criterion_step"] = steps
        best = self.state.get("best")
        trained = self.trained()
        if best is None or (trained, success, mean_return) > (
            best.get("trained", True),
            best["success"],
            best["mean_return"],
        ):
            self.state["best"] = {
                "step": steps,
                "success": success,
                "mean_return": mean_return,
                "trained": trained,
            }
            self.save_best()
        if success >= self.budget.target_success and self.state.get("target_step") is None:
            self.state["target_step"] = steps

    def _episode(self, ret: float, length: int, steps: int, success: bool = False, robot: int = 0) -> None:
        self.returns.append(ret)
        average = float(np.mean(self.returns[-STOP_WINDOW:]))
        window = self.returns[-self.criterion.window :]
        with (self.run / "curve.csv").open("a", newline="") as f:
            csv.writer(f).writerow(
                [
                    len(self.returns),
                    steps,
                    f"{ret:.6f}",
                    length,
                    f"{average:.6f}",
                    f"{self.pending_q0:.6f}",
                    int(success),
                    robot,
                ]
            )
        if (
            len(window) == self.criterion.window
            and float(np.mean(window)) >= self.criterion.threshold
            and self.state.get("criterion_step") is None
        ):
            self.state.update(criterion_step=steps, criterion_episode=len(self.returns))
        self.bar.set_postfix(episodes=len(self.returns), avg50=f"{average:.2f}", refresh=False)

    def _on_training_end(self) -> None:
        self.bar.close()


def train(
    algo: str,
    preset_name: str,
    seed: int,
    out: Path,
    budget: Budget | None = None,
    resume: bool = False,
    progress: bool = False,
    overrides: Sequence[str] = (),
    scenario: str = DEFAULT_SCENARIO,
    warn: Callable[[str], None] | None = None,
) -> dict[str, Any]:
    """Train one agent into ``out`` (or continue the run there) on a scenario; return its summary.

    ``overrides``: ``NAME=VALUE`` changes to the preset's hyperparameters (recorded in config.json and
    applied again on resume). ``warn`` is told, before any training, when the budget ends within the
    random warm-up (the run then trains nothing; its summary says ``untrained``)."""
    budget = budget or Budget()
    if algo not in ALGOS:
        raise UsageError(f"unknown algorithm {algo!r}; choose from {', '.join(ALGOS)}")
    torch.set_num_threads(1)  # reproducible, and parallel runs do not fight over cores
    if resume:
        saved = read_run_config(out)
        _refuse_a_fired_stop_rule(out, budget)
        _extend_budget(out, saved, budget)
        algo, preset_name, seed = saved["algo"], saved["preset"], saved["seed"]
        overrides = saved.get("overrides", [])
        scenario = saved.get("scenario", DEFAULT_SCENARIO)
    elif out.exists() and any(out.iterdir()):
        raise UsageError(f"run directory {out} is not empty; use --resume {out} to continue it")
    if algo == "recurrent-ppo" and scenario in SCENARIOS and SCENARIOS[scenario].robots > 1:
        raise UsageError(
            f"recurrent-ppo cannot train the {scenario} scenario: its one policy drives every robot, and a "
            "policy with memory holds one robot's state"
        )
    try:
        cfg = with_overrides(preset(algo, preset_name, scenario), overrides)
        if scenario == WALKER.name:
            deck_reward.variant(cfg.reward)
        else:
            check_options(cfg.reward, cfg.success_bonus, cfg.shaping_gain)
    except ValueError as exc:
        raise UsageError(str(exc)) from None
    idle = untrained_budget(cfg, budget.max_steps)
    if idle is not None and warn is not None:
        warn(idle)
    out.mkdir(parents=True, exist_ok=True)
    run = _Run(out, RunConfig(
        algo, preset_name, seed, scenario=scenario, hyperparameters=to_dict(cfg), budget=vars(budget),
        overrides=list(overrides),
    ), cfg, budget, resume)  # fmt: skip
    if not resume and isinstance(cfg, PPOConfig) and cfg.warm_start_demonstrations:
        run.save_model(WARM_START_MODEL)  # behaviour cloning alone, before any PPO update
    criterion = CRITERIA.get(scenario, Criterion())
    monitor = RunMonitor(
        out,
        budget,
        run.state,
        run.save,
        run.validate,
        progress,
        lambda: run.save_model(BEST_MODEL),
        run.trained,
        criterion,
    )
    remaining = budget.max_steps - int(run.state.get("steps", 0))
    if resume:
        _restore_random(run.generators, run.model)  # last: loading the model drew from them
    if remaining > 0:
        callbacks = CallbackList([monitor, *_episode_callbacks(out, run, criterion, monitor)])
        run.model.learn(remaining, callback=callbacks, reset_num_timesteps=not resume, tb_log_name="run")
    monitor.checkpoint()
    return run.finish(monitor.returns)


EPISODE_SUMS_FILE = "episode_sums.csv"
"""A run's per-episode sums of an env's ``EPISODE_KEYS`` (the walker's reward terms and distance)."""


def _episode_callbacks(out: Path, run: _Run, criterion: Criterion, monitor: RunMonitor) -> list[BaseCallback]:
    """The callbacks of a scenario's criteria and logs beyond :class:`RunMonitor`'s: saving agents above the
    save threshold, and the env's per-episode sums."""
    out_callbacks: list[BaseCallback] = []
    if criterion.save_above is not None:
        out_callbacks.append(
            SaveAboveThreshold(criterion.save_above, out / SAVED_AGENTS, lambda: monitor.returns)
        )
    keys = run.env.get_attr("EPISODE_KEYS")[0] if run.env.has_attr("EPISODE_KEYS") else ()
    if keys:
        out_callbacks.append(EpisodeSums(out / EPISODE_SUMS_FILE, keys))
    return out_callbacks


class _Run:
    """One training run's model, env and state in its folder: started fresh (config.json, curve.csv, a new
    model seeded with demonstrations) or loaded from its last complete checkpoint."""

    def __init__(self, out: Path, config: RunConfig, cfg: Any, budget: Budget, resume: bool) -> None:
        self.out, self.config, self.cfg, self.budget = out, config, cfg, budget
        self.scenario = config.scenario
        self.normalize = isinstance(cfg, PPOConfig) and cfg.normalize_observations
        self.state: dict[str, Any] = {}
        self.generators: dict[str, Any] = {}
        if resume:
            self.model, self.env, self.state, self.generators = _load_checkpoint(
                _complete_checkpoint(out), config.algo, out / "tb"
            )
            _truncate_curve(out / "curve.csv", len(self.state.get("returns", [])))
            if (out / EVALUATIONS_FILE).exists():
                _truncate_curve(out / EVALUATIONS_FILE, self.state.get("evaluations", 0))
            if (out / EPISODE_SUMS_FILE).exists():
                _truncate_curve(out / EPISODE_SUMS_FILE, len(self.state.get("returns", [])))
        else:
            self._start()
        self.state.setdefault("wall_clock_s", 0.0)
        self.started = time.monotonic()

    def _start(self) -> None:
        cfg, seed, scenario, out = self.cfg, self.config.seed, self.scenario, self.out
        self.env = make_env(self.normalize, seed, scenario, cfg)
        (out / "config.json").write_text(
            json.dumps({**vars(self.config), "provenance": provenance(), "machine": machine()}, indent=2)
        )
        with (out / "curve.csv").open("w", newline="") as f:
            csv.writer(f).writerow(CURVE_FIELDS)
        self.model = build_model(self.config.algo, cfg, self.env, seed, out / "tb")
        model = self.model
        if isinstance(model, OffPolicyAlgorithm) and not isinstance(cfg, PPOConfig) and cfg.demonstrations:
            seed_replay_buffer(model, cfg.demonstrations, cfg.demonstration_noise, seed, scenario, cfg)
        if (
            isinstance(model, PPO | RecurrentPPO)
            and isinstance(cfg, PPOConfig)
            and cfg.warm_start_demonstrations
        ):
            warm_start(
                model, self.env, cfg.warm_start_demonstrations, cfg.warm_start_epochs, seed, scenario, cfg
            )

    def trained(self) -> bool:
        """Whether the model has learnt anything: a training update, or PPO's behaviour-cloned start."""
        cloned = isinstance(self.cfg, PPOConfig) and self.cfg.warm_start_demonstrations > 0
        return cloned or int(getattr(self.model, "_n_updates", 0)) > 0

    def wall_clock_s(self) -> float:
        return float(self.state["wall_clock_s"]) + time.monotonic() - self.started

    def save(self) -> None:
        _save_checkpoint(self.out, self.model, self.env, {**self.state, "wall_clock_s": self.wall_clock_s()})

    def validate(self) -> tuple[float, float]:
        report = evaluate(
            _policy_of(self.model, self.env),
            self.budget.eval_episodes,
            VALIDATION_SEED,
            "validation",
            env_id=SCENARIOS[self.scenario].env_id,
            sample_time=SCENARIOS[self.scenario].sample_time_s,
            env_kwargs=env_kwargs(self.cfg),
        )
        return report.success_rate, report.mean_return

    def save_model(self, name: str) -> None:
        """The model as ``name``.zip, stamped, with its normalisation statistics as ``name``_vecnormalize."""
        out = self.out
        self.model.save(out / f"{name}.zip")
        stamp_model(
            out / f"{name}.zip",
            normalization_of(self.env) if self.normalize else None,
            self.scenario,
            len(SCENARIOS[self.scenario].observation),
        )
        if self.normalize:  # .npz for embedrl (safe to open), .pkl for SB3's VecNormalize.load
            save_normalization(self.env, out / f"{name}_vecnormalize.npz")
            self.env.save(str(out / f"{name}_vecnormalize.pkl"))  # type: ignore[attr-defined]

    def finish(self, returns: list[float]) -> dict[str, Any]:
        """Save the last model, select the run's model (best validated or last), write summary.json and
        the plots; the summary."""
        out, state, config = self.out, self.state, self.config
        self.save_model(LAST_MODEL)
        best = state.get("best")
        selected = BEST_MODEL if self.budget.select_best and best is not None else LAST_MODEL
        trained = best.get("trained", True) if selected == BEST_MODEL and best is not None else self.trained()
        shutil.copyfile(out / f"{selected}.zip", out / "model.zip")
        for suffix in (".npz", ".pkl"):
            if self.normalize:
                shutil.copyfile(out / f"{selected}_vecnormalize{suffix}", out / f"vecnormalize{suffix}")
        summary = {
            "algo": config.algo,
            "scenario": self.scenario,
            "preset": config.preset,
            "seed": config.seed,
            "criterion_reached": state.get("criterion_step") is not None,
            "episodes_to_criterion": state.get("criterion_episode"),
            "steps_to_criterion": state.get("criterion_step"),
            "first_deterministic_criterion_step": state.get("first_deterministic_criterion_step"),
            "validation_target": self.budget.target_success,
            "validation_target_step": state.get("target_step"),
            "selected": "best validation" if selected == BEST_MODEL else "last",
            "best_validation": best,
            "untrained": not trained,
            "total_steps": int(self.model.num_timesteps),
            "total_episodes": len(returns),
            "average50_at_stop": float(np.mean(returns[-STOP_WINDOW:])) if returns else None,
            "warmup_episodes": _episodes_within(out / "curve.csv", warmup_steps(self.cfg)),
            "demonstration_episodes": _demonstration_episodes(self.cfg),
            "updates": int(getattr(self.model, "_n_updates", 0)),
            "wall_clock_s": self.wall_clock_s(),
        }
        (out / "summary.json").write_text(json.dumps(summary, indent=2) + "\n")
        from embedrl.train.plots import plot_progress, plot_successes

        title = f"{config.algo.upper()} ({self.scenario}, {config.preset}, seed {config.seed})"
        plot_progress(out / "curve.csv", out / "progress.png", title, warmup_steps(self.cfg))
        plot_successes(out / "curve.csv", out / EVALUATIONS_FILE, out / "successes.png", title)
        self.env.close()
        return summary


def read_run_config(out: Path) -> dict[str, Any]:
    """A run directory's config.json (the run's algorithm, preset, seed, budget and overrides)."""
    from embedrl.train.config import check_run_config

    try:
        saved: dict[str, Any] = read_json(out / "config.json")
        check_run_config(saved)
    except FileNotFoundError:
        raise UsageError(f"cannot resume {out}: no config.json (not a run directory)") from None
    except (ValueError, KeyError, TypeError) as exc:
        raise UsageError(f"cannot resume {out}: config.json is damaged ({exc})") from None
    return saved


def _refuse_a_fired_stop_rule(out: Path, budget: Budget) -> None:
    """A run that stopped at its stop rule would stop again at once: resuming it to a larger budget
    under the same rule is refused, naming the option that trains on (before anything is changed)."""
    try:
        state = read_json(_complete_checkpoint(out) / "state.json")
        steps = int(state.get("steps", 0))
    except (OSError, ValueError, AttributeError, TypeError):
        return  # a damaged checkpoint: the checkpoint loader says what is wrong
    fired = stop_rule_fired(budget.stop, state)
    if fired is not None and budget.max_steps > steps:
        raise UsageError(
            f"{out} stopped at its stop rule (--stop {budget.stop}) at step {fired:,}; add --keep-training "
            f"to train on to {budget.max_steps:,} steps"
        )


def _extend_budget(out: Path, saved: dict[str, Any], budget: Budget) -> None:
    """A resumed run may train on past its step budget (recorded in config.json's ``budget`` and
    ``extensions``); a smaller budget than the run's is refused."""
    old = int(saved["budget"].get("max_steps", 0))
    if budget.max_steps < old:
        raise UsageError(f"{out} has a budget of {old} steps; resume it with at least that many")
    old_stop = saved["budget"].get("stop", "validation")
    if budget.max_steps == old and budget.stop == old_stop:
        return
    saved["budget"] = {**saved["budget"], "max_steps": budget.max_steps, "stop": budget.stop}
    saved["extensions"] = [
        *saved.get("extensions", []),
        {
            "from_max_steps": old,
            "to_max_steps": budget.max_steps,
            "from_stop": old_stop,
            "to_stop": budget.stop,
        },
    ]
    text = json.dumps(saved, indent=2)
    atomic_write(out / "config.json", lambda tmp: tmp.write_text(text))


def _complete_checkpoint(out: Path) -> Path:
    """The run's last complete checkpoint (``checkpoint/``, or ``checkpoint.old/`` if a kill came between
    the two renames of a swap); a clear error if there is none: never a silent fresh start."""
    for candidate in (out / "checkpoint", out / "checkpoint.old"):
        if (candidate / "state.json").is_file():
            return candidate
    raise UsageError(
        f"cannot resume {out}: no complete checkpoint (checkpoint/state.json); the run was stopped before "
        "its first checkpoint. Start it again with --out"
    )


def _save_checkpoint(out: Path, model: BaseAlgorithm, env: VecEnv, state: dict[str, Any]) -> None:
    """Write a complete checkpoint beside the current one, then swap: a complete one always exists."""
    tmp, current, old = out / "checkpoint.partial", out / "checkpoint", out / "checkpoint.old"
    shutil.rmtree(tmp, ignore_errors=True)
    tmp.mkdir()
    model.save(tmp / "model.zip")
    if isinstance(model, OffPolicyAlgorithm):
        model.save_replay_buffer(tmp / "replay_buffer.pkl")
    with (tmp / "env.pkl").open("wb") as f:  # the env mid-episode
        pickle.dump(env.venv if isinstance(env, VecNormalize) else env, f)
    if isinstance(env, VecNormalize):  # its pickle leaves out the env it wraps
        env.save(str(tmp / "vecnormalize.pkl"))
    with (tmp / "random.pkl").open("wb") as f:
        pickle.dump(
            {
                "python": random.getstate(),
                "numpy": np.random.get_state(),
                "torch": torch.get_rng_state(),
                "action_space": model.action_space.np_random.bit_generator.state,
            },
            f,
        )
    (tmp / "state.json").write_text(json.dumps(state))  # last: its presence marks a complete checkpoint
    if current.exists():
        shutil.rmtree(old, ignore_errors=True)
        os.replace(current, old)
    os.replace(tmp, current)
    shutil.rmtree(old, ignore_errors=True)


def _load_checkpoint(
    checkpoint: Path, algo: str, tb: Path
) -> tuple[BaseAlgorithm, VecEnv, dict[str, Any], dict[str, Any]]:
    """Model, training env, counters and random generators' states of a checkpoint (the run's own files:
    pickles it wrote itself)."""
    try:
        state: dict[str, Any] = read_json(checkpoint / "state.json")
        with (checkpoint / "random.pkl").open("rb") as f:
            generators: dict[str, Any] = pickle.load(f)
        with (checkpoint / "env.pkl").open("rb") as f:
            env: VecEnv = pickle.load(f)
        if (checkpoint / "vecnormalize.pkl").is_file():
            env = VecNormalize.load(str(checkpoint / "vecnormalize.pkl"), env)
        model = CLASSES[algo].load(
            checkpoint / "model.zip", env=env, device="cpu", tensorboard_log=str(tb), force_reset=False
        )
        if isinstance(model, OffPolicyAlgorithm):
            model.load_replay_buffer(checkpoint / "replay_buffer.pkl")
    except Exception as exc:  # any damage: a truncated pickle, a bad zip, a missing file
        raise UsageError(
            f"cannot resume from {checkpoint}: it is damaged ({type(exc).__name__}: {exc}); "
            "start the run again with --out"
        ) from None
    return model, env, state, generators


def _restore_random(saved: dict[str, Any], model: BaseAlgorithm) -> None:
    random.setstate(saved["python"])
    np.random.set_state(saved["numpy"])
    torch.set_rng_state(saved["torch"])
    model.action_space.np_random.bit_generator.state = saved["action_space"]


class _ModelPolicy:
    """A model's deterministic action on raw observations, normalised as in training; a recurrent model
    carries its LSTM state through an episode (``reset`` at each start: :func:`evaluate.start_episode`)."""

    def __init__(self, model: BaseAlgorithm, env: VecEnv) -> None:
        self.model, self.env = model, env
        self.state: Any = None
        self.start = True

    def reset(self) -> None:
        self.state, self.start = None, True

    def __call__(self, obs: np.ndarray) -> np.ndarray:
        x = self.env.normalize_obs(obs) if isinstance(self.env, VecNormalize) else obs
        if not isinstance(self.model, RecurrentPPO):
            return np.asarray(self.model.predict(x, deterministic=True)[0], dtype=np.float32)
        action, self.state = self.model.predict(
            x, self.state, episode_start=np.array([self.start]), deterministic=True
        )
        self.start = False
        return np.asarray(action, dtype=np.float32)


def _policy_of(model: BaseAlgorithm, env: VecEnv) -> Callable[[np.ndarray], np.ndarray]:
    return _ModelPolicy(model, env)


def _demonstration_episodes(cfg: Any) -> int:
    """Episodes of the potential-field controller the agent learnt from before training (not in the curve)."""
    return int(cfg.warm_start_demonstrations if isinstance(cfg, PPOConfig) else cfg.demonstrations)


def _episodes_within(curve: Path, steps: int) -> int:
    """Training episodes that ended within the first ``steps`` env steps (the random warm-up)."""
    with curve.open() as f:
        return sum(int(row["steps"]) <= steps for row in csv.DictReader(f))


def _truncate_curve(path: Path, episodes: int) -> None:
    """Drop rows logged after the checkpoint: the resumed run repeats those episodes (or evaluations)."""
    rows = path.read_text().splitlines()
    path.write_text("\n".join(rows[: episodes + 1]) + "\n")
