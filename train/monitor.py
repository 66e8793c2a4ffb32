"""What a run watches while it trains: the study's stop criterion per scenario, the curve (one row per
episode, the critic's Q0), the validation evaluations, the agents saved above a return, per-episode sums."""

from __future__ import annotations

import csv
from collections.abc import Callable, Sequence
from dataclasses import dataclass
from pathlib import Path
from typing import Any

import numpy as np
import torch
from sb3_contrib import RecurrentPPO
from stable_baselines3 import PPO, SAC
from stable_baselines3.common.base_class import BaseAlgorithm
from stable_baselines3.common.callbacks import BaseCallback
from tqdm import tqdm

from embedrl.train.config import (
    Budget,
)
from embedrl.train.scenarios import WALKER

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
EVALUATIONS_FILE = "evaluations.csv"
EVALUATION_FIELDS = ("steps", "success_rate", "mean_return")
"""evaluations.csv: one row per validation evaluation."""
CURVE_FIELDS = ("episode", "steps", "return", "length", "average50", "q0", "success", "robot")
"""curve.csv's columns; ``robot`` is the robot's index (two robots share one policy and one curve)."""


def q0(model: BaseAlgorithm, obs: np.ndarray) -> float:
    """The critic's estimate of a state's value (MATLAB's Episode Q0)."""
    from embedrl.train.jax_agents import is_jax_model, jax_q0

    if is_jax_model(model):
        return jax_q0(model, obs)
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


EPISODE_SUMS_FILE = "episode_sums.csv"
"""A run's per-episode sums of an env's ``EPISODE_KEYS`` (the walker's reward terms and distance)."""
