"""An example policy trained in a minute: ``python -m embedrl.export.example OUT.zip``.

A TD3 model with the reference study's actor (6 -> 100 -> 100 -> 2, ReLU, tanh) whose actor is
trained by imitation of the potential-field controller (DAgger: roll out the learner, label every
visited observation with the controller's action, retrain on everything). The result is a real SB3
model of the deployed size that drives the robot through the gap, so the export's closed-loop
check has something meaningful to compare. Seeded: the same command gives the same model.
"""

from __future__ import annotations

import sys
from pathlib import Path

import gymnasium as gym
import numpy as np
import torch

from embedrl import train
from embedrl.common import EXAMPLE_SEED
from embedrl.train.potential_field import PotentialFieldController

ROUNDS = 4
"""DAgger rounds after the initial demonstrations."""
EPISODES_PER_ROUND = 100
EPOCHS = 60
BATCH = 256
LEARNING_RATE = 1e-3
SEED = 0


def _rollouts(env: gym.Env[np.ndarray, np.ndarray], act: object, first_seed: int) -> np.ndarray:
    observations = []
    for episode in range(EPISODES_PER_ROUND):
        obs, _ = env.reset(seed=first_seed + episode)
        done = False
        while not done:
            observations.append(obs)
            obs, _, terminated, truncated, _ = env.step(act(obs))  # type: ignore[operator]
            done = terminated or truncated
    return np.array(observations, dtype=np.float32)


def main(out: Path) -> None:
    from stable_baselines3 import TD3

    torch.manual_seed(SEED)
    env = gym.make(train.ENV_ID)
    model = TD3(
        "MlpPolicy", env, policy_kwargs={"net_arch": [100, 100]}, seed=SEED, device="cpu", buffer_size=1
    )
    actor = model.policy.actor
    expert = PotentialFieldController()

    def learner(obs: np.ndarray) -> np.ndarray:
        return np.asarray(model.predict(obs, deterministic=True)[0], dtype=np.float32)

    data = _rollouts(env, expert, EXAMPLE_SEED)
    optimizer = torch.optim.Adam(actor.parameters(), lr=LEARNING_RATE)
    generator = torch.Generator().manual_seed(SEED)
    for round_ in range(ROUNDS + 1):
        if round_:
            data = np.concatenate([data, _rollouts(env, learner, EXAMPLE_SEED + round_ * EPISODES_PER_ROUND)])
        x = torch.as_tensor(data)
        y = torch.as_tensor(np.array([expert(o) for o in data]))
        for _ in range(EPOCHS):
            order = torch.randperm(len(x), generator=generator)
            for start in range(0, len(x), BATCH):
                idx = order[start : start + BATCH]
                loss = torch.nn.functional.mse_loss(actor(x[idx]), y[idx])
                optimizer.zero_grad()
                loss.backward()  # type: ignore[no-untyped-call]
                optimizer.step()
        print(f"round {round_}: {len(data)} labelled observations, loss {loss.item():.4f}")
    model.policy.actor_target.load_state_dict(actor.state_dict())
    out.parent.mkdir(parents=True, exist_ok=True)
    model.save(out)
    print(f"wrote {out} (TD3 actor 6-100-100-2 imitating the potential-field controller, seed {SEED})")


if __name__ == "__main__":
    main(Path(sys.argv[1]))
