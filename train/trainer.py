"""Training runs: the loop that trains an SB3 agent, evaluates it, checkpoints and resumes it. The env and
agent are :mod:`train.agents`, the demonstrations :mod:`train.demonstrations`, the stop criterion, curve and
callbacks :mod:`train.monitor`, the run folder and its checkpoint :mod:`train.checkpoints`.

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
import json
import shutil
import time
from collections.abc import Callable, Sequence
from pathlib import Path
from typing import Any

import numpy as np
import torch
from sb3_contrib import RecurrentPPO
from stable_baselines3 import PPO
from stable_baselines3.common.base_class import BaseAlgorithm
from stable_baselines3.common.callbacks import BaseCallback, CallbackList
from stable_baselines3.common.off_policy_algorithm import OffPolicyAlgorithm
from stable_baselines3.common.vec_env import VecEnv, VecNormalize

from embedrl.common import VALIDATION_SEED, provenance
from embedrl.train import deck_reward
from embedrl.train.agents import build_model, env_kwargs, make_env, model_class
from embedrl.train.checkpoints import (
    complete_checkpoint,
    episodes_within,
    extend_budget,
    load_checkpoint,
    read_run_config,
    refuse_a_fired_stop_rule,
    restore_random,
    save_checkpoint,
    truncate_curve,
)
from embedrl.train.config import (
    ALGOS,
    Budget,
    PPOConfig,
    RunConfig,
    preset,
    to_dict,
    untrained_budget,
    warmup_steps,
    with_overrides,
)
from embedrl.train.demonstrations import demonstration_episodes, seed_replay_buffer, warm_start
from embedrl.train.errors import UsageError
from embedrl.train.evaluate import evaluate
from embedrl.train.jax_agents import is_jax_model, save_as_torch
from embedrl.train.models import normalization_of, save_normalization, stamp_model
from embedrl.train.monitor import (
    CRITERIA,
    CURVE_FIELDS,
    EPISODE_SUMS_FILE,
    EVALUATIONS_FILE,
    SAVED_AGENTS,
    STOP_WINDOW,
    Criterion,
    EpisodeSums,
    RunMonitor,
    SaveAboveThreshold,
)
from embedrl.train.portable import machine
from embedrl.train.rewards import check_options
from embedrl.train.scenarios import DEFAULT_SCENARIO, SCENARIOS, WALKER

BEST_MODEL = "best_model"
"""The checkpoint with the best validation evaluation so far (``best_model.zip``)."""
WARM_START_MODEL = "warm_start_model"
"""PPO's behaviour-cloned start before any PPO update (``warm_start_model.zip``): what cloning alone gives."""
LAST_MODEL = "last_model"
"""The model when training ended (``last_model.zip``)."""


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
        refuse_a_fired_stop_rule(out, budget)
        extend_budget(out, saved, budget)
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
        restore_random(run.generators, run.model)  # last: loading the model drew from them
    if remaining > 0:
        callbacks = CallbackList([monitor, *_episode_callbacks(out, run, criterion, monitor)])
        run.model.learn(remaining, callback=callbacks, reset_num_timesteps=not resume, tb_log_name="run")
    monitor.checkpoint()
    return run.finish(monitor.returns)


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
            self.model, self.env, self.state, self.generators = load_checkpoint(
                complete_checkpoint(out), config.algo, out / "tb", model_class(config.algo, cfg)
            )
            truncate_curve(out / "curve.csv", len(self.state.get("returns", [])))
            if (out / EVALUATIONS_FILE).exists():
                truncate_curve(out / EVALUATIONS_FILE, self.state.get("evaluations", 0))
            if (out / EPISODE_SUMS_FILE).exists():
                truncate_curve(out / EPISODE_SUMS_FILE, len(self.state.get("returns", [])))
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
        save_checkpoint(self.out, self.model, self.env, {**self.state, "wall_clock_s": self.wall_clock_s()})

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
        if is_jax_model(self.model):  # an SB3 torch zip, checked against the JAX actor
            save_as_torch(self.model, out / f"{name}.zip")
        else:
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
            "warmup_episodes": episodes_within(out / "curve.csv", warmup_steps(self.cfg)),
            "demonstration_episodes": demonstration_episodes(self.cfg),
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
