"""Parallel experience workers, as the deck trains (MATLAB's ``UseParallel``, asynchronous, each worker
sending its experiences every 32 steps): N Ray actors collect, one learner updates.

Each worker runs its own env with a copy of the actor's weights (a NumPy forward pass, ReLU layers and a tanh
output) and Gaussian exploration noise, and sends its ``block`` transitions at a time. The learner takes the
first block to arrive (``ray.wait``: asynchronous, a slow worker holds no one up), adds it to its replay
buffer, makes one update per transition (the run's update-to-data ratio stays 1, as in one process) and
gives the worker the actor's new weights with its next request. Before ``learning_starts`` transitions the
workers act uniformly at random. With one worker the loop is sequential: a seed repeats exactly.

Ray is the engine on one machine and on a cluster alike: ``local`` starts Ray on this machine (N worker
processes), an address joins a running cluster. The run folder holds what a one-process run's holds for
deployment (``model.zip``, an SB3 torch zip, ``config.json``, ``curve.csv``, ``evaluations.csv``,
``summary.json``) plus ``throughput.json``: the learner's updates per second of its own time, each worker's
env steps per second of its own time, and the wall-clock rate, from which the rate of N workers on a cluster
is read (docs/walker.md).
"""

from __future__ import annotations

import csv
import json
import time
from collections.abc import Callable, Sequence
from dataclasses import replace
from pathlib import Path
from typing import Any

import numpy as np

from embedrl.common import VALIDATION_SEED, provenance
from embedrl.train.config import Budget, TD3Config, preset, to_dict, with_overrides
from embedrl.train.errors import UsageError
from embedrl.train.scenarios import SCENARIOS

DEFAULT_BLOCK = 32
"""Transitions a worker sends at a time (the deck's workers send every 32 steps)."""
WORKER_SEED_STRIDE = 10_007
"""Worker ``i`` seeds its env and noise with ``seed + (i + 1) * stride``: apart from each other and from the
learner's seed."""
MAX_WORKERS = 256
THROUGHPUT_FILE = "throughput.json"


def actor_layers(model: Any) -> list[tuple[np.ndarray, np.ndarray]]:
    """The deterministic actor's (kernel [in, out], bias) per layer, from an sbx or an SB3 TD3."""
    from embedrl.train.jax_agents import _dense_layers, is_jax_model

    if is_jax_model(model):
        return _dense_layers(model.policy.actor_state.params["params"])
    import torch

    linears = [m for m in model.policy.actor.modules() if isinstance(m, torch.nn.Linear)]
    return [(m.weight.detach().numpy().T.copy(), m.bias.detach().numpy().copy()) for m in linears]


def forward(layers: Sequence[tuple[np.ndarray, np.ndarray]], obs: np.ndarray) -> np.ndarray:
    """The actor on one observation: ReLU between layers, tanh at the end (actions in [-1, 1])."""
    x = np.asarray(obs, dtype=np.float32)
    for k, (kernel, bias) in enumerate(layers):
        x = x @ kernel + bias
        x = np.tanh(x) if k == len(layers) - 1 else np.maximum(x, 0.0)
    return x


class ExperienceWorker:
    """One env and its exploration: ``collect`` runs ``block`` steps with the weights it is given."""

    def __init__(self, env_id: str, env_kwargs: dict[str, Any], seed: int, noise_sigma: float) -> None:
        import gymnasium as gym

        import embedrl.train  # noqa: F401  (registers the scenarios' envs in this process)

        self.env = gym.make(env_id, **env_kwargs)
        self.rng = np.random.default_rng(seed)
        self.noise_sigma = noise_sigma
        self.obs, _ = self.env.reset(seed=seed)
        self.episode_return, self.episode_steps = 0.0, 0
        space = self.env.action_space
        self.low, self.high = np.asarray(space.low), np.asarray(space.high)  # type: ignore[attr-defined]
        self.busy_s = 0.0

    def collect(self, layers: list[tuple[np.ndarray, np.ndarray]] | None, block: int) -> dict[str, Any]:
        """``block`` transitions (actions scaled to [-1, 1], as SB3's buffer keeps them; ``done`` only where
        the episode terminated, so a time limit is bootstrapped), the episodes that ended, and this worker's
        busy time. ``layers`` None: uniform random actions (the warm-up)."""
        start = time.process_time()
        rows: dict[str, list[Any]] = {k: [] for k in ("obs", "next_obs", "action", "reward", "done")}
        episodes = []
        for _ in range(block):
            if layers is None:
                scaled = self.rng.uniform(-1.0, 1.0, size=self.low.shape).astype(np.float32)
            else:
                noise = self.rng.normal(0.0, self.noise_sigma, size=self.low.shape)
                scaled = np.clip(forward(layers, self.obs) + noise, -1.0, 1.0).astype(np.float32)
            action = self.low + (scaled + 1.0) * 0.5 * (self.high - self.low)
            next_obs, reward, terminated, truncated, _ = self.env.step(action)
            for key, value in zip(rows, (self.obs, next_obs, scaled, reward, terminated), strict=True):
                rows[key].append(value)
            self.episode_return += float(reward)
            self.episode_steps += 1
            self.obs = next_obs
            if terminated or truncated:
                episodes.append((self.episode_return, self.episode_steps))
                self.obs, _ = self.env.reset()
                self.episode_return, self.episode_steps = 0.0, 0
        self.busy_s += time.process_time() - start
        arrays = {k: np.asarray(v, dtype=np.float32) for k, v in rows.items()}
        return {**arrays, "episodes": episodes, "busy_s": self.busy_s}


def train_parallel(
    preset_name: str,
    seed: int,
    out: Path,
    budget: Budget,
    workers: int,
    block: int = DEFAULT_BLOCK,
    address: str = "local",
    scenario: str = "walker",
    overrides: Sequence[str] = (),
    log: Callable[[str], None] = print,
) -> dict[str, Any]:
    """Train TD3 with ``workers`` Ray experience workers into ``out``; its summary."""
    import ray

    if not 1 <= workers <= MAX_WORKERS:
        raise UsageError(f"--workers must be within 1..{MAX_WORKERS}, got {workers}")
    if out.exists() and any(out.iterdir()):
        raise UsageError(f"run directory {out} is not empty; a run with --workers starts in a new folder")
    try:
        cfg = with_overrides(preset("td3", preset_name, scenario), overrides)
    except ValueError as exc:
        raise UsageError(str(exc)) from None
    assert isinstance(cfg, TD3Config)
    out.mkdir(parents=True)
    record = {"algo": "td3", "preset": preset_name, "seed": seed, "scenario": scenario, "workers": workers,
              "block": block, "ray": address, "hyperparameters": to_dict(cfg), "budget": vars(budget),
              "overrides": list(overrides), "provenance": provenance()}  # fmt: skip
    (out / "config.json").write_text(json.dumps(record, indent=2))
    local = address == "local"
    if not ray.is_initialized():  # before JAX starts its threads: Ray forks its own processes
        ray.init(
            address=None if local else address, num_cpus=workers + 1 if local else None,
            include_dashboard=False, log_to_driver=False, configure_logging=False,
        )  # fmt: skip
    learner = _Learner(cfg, seed, scenario, out, budget, log)
    remote: Any = ray.remote(num_cpus=1)(ExperienceWorker)
    pool: list[Any] = [
        remote.remote(SCENARIOS[scenario].env_id, learner.env_kwargs, seed + (k + 1) * WORKER_SEED_STRIDE,
                      cfg.noise_sigma)
        for k in range(workers)
    ]  # fmt: skip

    def request(k: int) -> Any:
        warm = learner.steps < cfg.learning_starts
        return pool[k].collect.remote(None if warm else actor_layers(learner.model), block)

    pending = {request(k): k for k in range(workers)}
    try:
        while pending:  # the first block to arrive, whichever worker sent it
            ready, _ = ray.wait(list(pending), num_returns=1)
            k = pending.pop(ready[0])
            learner.take(ray.get(ready[0]), k)
            if learner.steps + block * len(pending) < budget.max_steps:
                pending[request(k)] = k
    finally:
        learner.curve.close()
        if local:
            ray.shutdown()
    return learner.finish(workers, block)


class _Learner:
    """The run's TD3, its replay buffer, its logs and its counters."""

    def __init__(
        self, cfg: TD3Config, seed: int, scenario: str, out: Path, budget: Budget, log: Callable[[str], None]
    ) -> None:
        from stable_baselines3.common.logger import configure

        from embedrl.train.agents import build_model, env_kwargs, make_env

        self.cfg, self.scenario, self.out, self.budget, self.log = cfg, scenario, out, budget, log
        self.env_kwargs = env_kwargs(cfg)
        env = make_env(False, seed, scenario, cfg)
        self.model: Any = build_model("td3", replace(cfg, learning_starts=0), env, seed, None)
        self.model.set_logger(configure(None, []))
        self.curve = (out / "curve.csv").open("w", newline="")
        self.writer = csv.writer(self.curve)
        self.writer.writerow(("episode", "steps", "return", "length", "worker"))
        self.evaluations: list[tuple[int, float, float]] = []
        self.steps, self.episodes, self.learner_s = 0, 0, 0.0
        self.best: dict[str, Any] | None = None
        self.next_eval = budget.eval_every
        self.busy: dict[int, float] = {}
        self.started = time.monotonic()

    def take(self, batch: dict[str, Any], worker: int) -> None:
        """Worker ``worker``'s block into the buffer, one update per transition, a validation when due."""
        self.busy[worker] = batch["busy_s"]
        n = len(batch["reward"])
        for i in range(n):
            self.model.replay_buffer.add(
                batch["obs"][i : i + 1], batch["next_obs"][i : i + 1], batch["action"][i : i + 1],
                batch["reward"][i : i + 1], batch["done"][i : i + 1], [{}],
            )  # fmt: skip
        self.steps += n
        for episode_return, length in batch["episodes"]:
            self.episodes += 1
            self.writer.writerow((self.episodes, self.steps, f"{episode_return:.6f}", length, worker))
        if self.steps > self.cfg.learning_starts:
            start = time.process_time()
            self.model.train(gradient_steps=n, batch_size=self.cfg.batch_size)
            self.learner_s += time.process_time() - start
        self.model.num_timesteps = self.steps
        if self.steps >= self.next_eval or self.steps >= self.budget.max_steps:
            self.next_eval += self.budget.eval_every
            success, mean_return = _validate(
                self.model, self.budget, SCENARIOS[self.scenario], self.env_kwargs
            )
            self.evaluations.append((self.steps, success, mean_return))
            self.log(f"{self.steps:,} steps: validation success {success:.0%}, mean return {mean_return:.1f}")
            if self.best is None or (success, mean_return) > (self.best["success"], self.best["mean_return"]):
                self.best = {"step": self.steps, "success": success, "mean_return": mean_return}
                _save(self.model, self.out / "best_model.zip", self.scenario)

    def finish(self, workers: int, block: int) -> dict[str, Any]:
        """The last and the selected model, evaluations.csv, throughput.json and summary.json."""
        out, best = self.out, self.best
        wall_s = time.monotonic() - self.started
        _save(self.model, out / "last_model.zip", self.scenario)
        chosen = out / (
            "best_model.zip" if best is not None and self.budget.select_best else "last_model.zip"
        )
        (out / "model.zip").write_bytes(chosen.read_bytes())
        with (out / "evaluations.csv").open("w", newline="") as f:
            csv.writer(f).writerows([("steps", "success_rate", "mean_return"), *self.evaluations])
        updates = int(self.model._n_updates)
        throughput = {
            "workers": workers,
            "block": block,
            "steps": self.steps,
            "wall_s": round(wall_s, 1),
            "steps_per_wall_s": round(self.steps / wall_s, 1),
            "learner_updates_per_s": round(updates / self.learner_s, 1) if self.learner_s else None,
            "worker_steps_per_s": {
                str(k): round(self.steps / workers / s, 1) for k, s in sorted(self.busy.items()) if s
            },
        }
        (out / THROUGHPUT_FILE).write_text(json.dumps(throughput, indent=2) + "\n")
        summary = {
            "algo": "td3", "scenario": self.scenario, "workers": workers,
            "selected": "best validation" if chosen.name == "best_model.zip" else "last",
            "best_validation": best,
            "total_steps": self.steps, "total_episodes": self.episodes, "updates": updates,
            **{k: v for k, v in throughput.items() if k not in ("workers", "block", "steps")},
        }  # fmt: skip
        (out / "summary.json").write_text(json.dumps(summary, indent=2) + "\n")
        return summary


def _validate(learner: Any, budget: Budget, spec: Any, kwargs: dict[str, Any]) -> tuple[float, float]:
    from embedrl.train.evaluate import evaluate

    def policy(obs: np.ndarray) -> np.ndarray:
        return np.asarray(learner.predict(obs, deterministic=True)[0], dtype=np.float32)

    report = evaluate(
        policy, budget.eval_episodes, VALIDATION_SEED, "validation", env_id=spec.env_id,
        sample_time=spec.sample_time_s, env_kwargs=kwargs,
    )  # fmt: skip
    return report.success_rate, report.mean_return


def _save(model: Any, path: Path, scenario: str) -> None:
    """The model as an SB3 torch zip, stamped with its scenario (no normalisation)."""
    from embedrl.train.jax_agents import is_jax_model, save_as_torch
    from embedrl.train.models import stamp_model

    if is_jax_model(model):
        save_as_torch(model, path)
    else:
        model.save(path)
    stamp_model(path, None, scenario, len(SCENARIOS[scenario].observation))
