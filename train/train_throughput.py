"""Training speed benchmark: the walker's TD3 on SB3's torch against the same TD3 on sbx-rl's JAX.

Both sides learn with the walker's preset (its network, batch and block of ``train_freq`` steps with as
many updates), on one thread each (torch's ``set_num_threads(1)``; XLA's single-threaded CPU client), in the
same process one after the other. The figure is env steps per CPU second while learning (collection and
updates, after a warm-up that fills the replay buffer and compiles JAX's programs): the ratio is what the
backend gains on the same work and the same CPU.
"""

from __future__ import annotations

import time
from dataclasses import replace
from typing import Any

import torch
from tqdm import tqdm

from embedrl.common import on_terminal
from embedrl.train.agents import build_model, make_env
from embedrl.train.config import BACKENDS, TD3Config, preset
from embedrl.train.portable import machine
from embedrl.train.scenarios import WALKER

WARMUP_STEPS = 1_000
"""Random steps before learning starts (and before timing): the replay buffer's first mini-batches."""


def steps_per_cpu_second(backend: str, steps: int, seed: int, scenario: str = WALKER.name) -> float:
    """Env steps per CPU second of TD3 with the scenario's tuned preset on ``backend``."""
    cfg = preset("td3", "tuned", scenario)
    assert isinstance(cfg, TD3Config)
    cfg = replace(cfg, backend=backend, learning_starts=WARMUP_STEPS)
    env = make_env(False, seed, scenario, cfg)
    model = build_model("td3", cfg, env, seed, None)
    model.learn(WARMUP_STEPS + 2 * cfg.train_freq)  # the buffer, and JAX's programs compiled
    start = time.process_time()
    model.learn(steps, reset_num_timesteps=False)
    seconds = time.process_time() - start
    env.close()
    return steps / seconds


def run(steps: int, seed: int, scenario: str = WALKER.name) -> dict[str, Any]:
    """Both backends on ``steps`` learning steps each; their rates and the ratio jax / torch."""
    torch.set_num_threads(1)
    cfg = preset("td3", "tuned", scenario)
    assert isinstance(cfg, TD3Config)
    rates = {}
    for backend in tqdm(BACKENDS, desc=f"TD3 on each backend, {steps:,} steps", disable=not on_terminal()):
        rates[backend] = steps_per_cpu_second(backend, steps, seed, scenario)
    return {
        "scenario": scenario,
        "network": list(cfg.net_arch),
        "block": cfg.train_freq,
        "batch_size": cfg.batch_size,
        "steps": steps,
        "torch_steps_per_cpu_s": round(rates["torch"], 1),
        "jax_steps_per_cpu_s": round(rates["jax"], 1),
        "jax_over_torch": round(rates["jax"] / rates["torch"], 2),
        "cpu": machine().get("cpu"),
    }
