"""Environment speed benchmark: env steps per second on one core with random actions.

The reference measured in the same run, with the same harness, is gymnasium's
``Pendulum-v1`` (a one-line numpy physics step): the ratio says how much the
warehouse's pymunk physics and collision checks cost against a minimal control env.
"""

from __future__ import annotations

import time
from dataclasses import dataclass

import gymnasium as gym
import numpy as np
from tqdm import tqdm

from embedrl.common import on_terminal
from embedrl.train import ENV_ID

TARGET_STEPS_PER_SECOND = 10_000
"""The warehouse env's floor: training at 200,000 steps stays within minutes of env time."""
REFERENCE_ENV_ID = "Pendulum-v1"


@dataclass(frozen=True)
class SpeedResult:
    env_id: str
    steps: int
    seconds: float

    @property
    def steps_per_second(self) -> float:
        return self.steps / self.seconds


def measure(env_id: str, steps: int, seed: int, repeats: int = 3) -> SpeedResult:
    """Best of ``repeats`` runs of ``steps`` steps of ``gym.make(env_id)`` with seeded uniform actions.

    Actions are drawn before timing; resets after episode ends are timed (a user's loop has them).
    """
    env = gym.make(env_id)
    space = env.action_space
    assert isinstance(space, gym.spaces.Box)
    rng = np.random.default_rng(seed)
    actions = rng.uniform(space.low, space.high, size=(steps, *space.shape)).astype(space.dtype)
    best = float("inf")
    # a bar per round, outside the timed loop; quiet when not a terminal
    for r in tqdm(range(repeats), desc=f"{env_id}: rounds of {steps:,} steps", disable=not on_terminal()):
        env.reset(seed=seed + r)
        start = time.perf_counter()
        for a in actions:
            _, _, terminated, truncated, _ = env.step(a)
            if terminated or truncated:
                env.reset()
        best = min(best, time.perf_counter() - start)
    env.close()
    return SpeedResult(env_id, steps, best)


def run(steps: int, seed: int) -> dict[str, float | int | str]:
    """Measure the warehouse env and the reference; return the numbers the CLI prints and saves."""
    ours = measure(ENV_ID, steps, seed)
    ref = measure(REFERENCE_ENV_ID, steps, seed)
    return {
        "env_id": ENV_ID,
        "steps": steps,
        "steps_per_second": round(ours.steps_per_second),
        "us_per_step": round(1e6 / ours.steps_per_second, 2),
        "target_steps_per_second": TARGET_STEPS_PER_SECOND,
        "ratio_to_target": round(ours.steps_per_second / TARGET_STEPS_PER_SECOND, 2),
        "reference_env_id": REFERENCE_ENV_ID,
        "reference_steps_per_second": round(ref.steps_per_second),
        "ratio_to_reference": round(ours.steps_per_second / ref.steps_per_second, 3),
    }
