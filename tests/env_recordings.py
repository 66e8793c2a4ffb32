"""Recorded episodes of every scenario, as digests: what keeps the shipped policies and tables valid.

``python -m tests.env_recordings`` writes ``tests/golden/env_recordings.json``; ``tests/test_env_speed.py``
plays the same episodes and compares. Each scenario runs on one env instance (so what a reset leaves
behind in the physics counts): random actions (drawn a little beyond [-1, 1] so that clipping counts) from
a seeded first reset on through unseeded resets, then the potential-field controller on seeded episodes
(long paths that end at the goal line or in a contact). A digest covers every observation, reward, flag,
what was hit and the pose after every step, bit for bit.
"""

from __future__ import annotations

import hashlib
import json
import struct
import sys
from pathlib import Path
from typing import Any

import numpy as np

GOLDEN = Path(__file__).parent / "golden" / "env_recordings.json"
RANDOM_EPISODES = 100
CONTROLLER_EPISODES = 6
ACTION_BOUND = 1.2
"""Random actions are drawn in [-ACTION_BOUND, ACTION_BOUND]: the env clips them to [-1, 1]."""


class _Digest:
    def __init__(self) -> None:
        self.h = hashlib.sha256()

    def add(self, *values: Any) -> None:
        for v in values:
            if isinstance(v, np.ndarray):
                self.h.update(np.ascontiguousarray(v).tobytes())
            elif isinstance(v, bool | type(None) | str):
                self.h.update(repr(v).encode())
            else:
                self.h.update(struct.pack("<d", float(v)))

    def hex(self) -> str:
        return self.h.hexdigest()[:16]


def _random_single(env_id: str) -> list[str]:
    import gymnasium as gym

    env: Any = gym.make(env_id).unwrapped
    rng = np.random.default_rng(12345)
    digests = []
    for episode in range(RANDOM_EPISODES):
        d = _Digest()
        obs, _ = env.reset(seed=7 if episode == 0 else None)
        d.add(obs)
        while True:
            action = rng.uniform(-ACTION_BOUND, ACTION_BOUND, 2).astype(np.float32)
            obs, r, term, trunc, info = env.step(action)
            d.add(obs, r, bool(term), bool(trunc), info["collided_with"], *env.trajectory[-1])
            if term or trunc:
                break
        digests.append(d.hex())
    env.close()
    return digests


def _random_pair() -> list[str]:
    from embedrl.train.two_robots_env import WarehouseTwoRobotsEnv

    env = WarehouseTwoRobotsEnv()
    rng = np.random.default_rng(12345)
    digests = []
    for episode in range(RANDOM_EPISODES):
        d = _Digest()
        obs, _ = env.reset(seed=7 if episode == 0 else None)
        d.add(*(obs[a] for a in sorted(obs)))
        while env.agents:
            actions = {a: rng.uniform(-ACTION_BOUND, ACTION_BOUND, 2).astype(np.float32) for a in env.agents}
            obs, rew, term, trunc, _ = env.step(actions)
            for a in sorted(obs):
                d.add(obs[a], rew[a], bool(term[a]), bool(trunc[a]))
            d.add(*env.outcomes, *(p for t in env.trajectories for p in t[-1]))
        digests.append(d.hex())
    env.close()
    return digests


def _controller(scenario: str, env_id: str) -> list[str]:
    from embedrl.train.evaluate import evaluate
    from embedrl.train.potential_field import PotentialFieldController

    report = evaluate(
        PotentialFieldController(scenario=scenario), CONTROLLER_EPISODES, 3, "pf", env_id=env_id
    )
    digests = []
    for r in report.results:
        d = _Digest()
        d.add(
            r.outcome, r.collided_with, r.episode_return, r.steps, *(p for pose in r.trajectory for p in pose)
        )
        digests.append(d.hex())
    return digests


def record() -> dict[str, dict[str, list[str]]]:
    """Every warehouse scenario's digests: ``{scenario: {"random": [...], "potential-field": [...]}}``."""
    from embedrl.train.scenarios import SCENARIOS, TWO_ROBOTS, WAREHOUSE

    out = {}
    for name in WAREHOUSE:
        spec = SCENARIOS[name]
        random = _random_pair() if spec is TWO_ROBOTS else _random_single(spec.env_id)
        out[name] = {"random": random, "potential-field": _controller(name, spec.env_id)}
    return out


if __name__ == "__main__":
    GOLDEN.write_text(json.dumps(record(), indent=1) + "\n")
    sys.stdout.write(f"wrote {GOLDEN}\n")
