"""TD3 on JAX (sbx-rl, SB3's JAX sibling), saved as an SB3 torch TD3 so every later stage reads it unchanged.

sbx's TD3 is an SB3 ``BaseAlgorithm``: the trainer's callbacks, checkpoints and resume work on it as on SB3's.
Its updates run as one compiled XLA program per ``train_freq`` block (``gradient_steps`` updates), which on a
small network is several times the env steps per CPU second of SB3's torch TD3 (``embedrl bench-train``).

What leaves a run (``model.zip``, ``best_model.zip``, ``last_model.zip``) is an SB3 TD3 zip with the same
actor and critic weights (Flax's ``Dense`` kernel is the transpose of torch's ``Linear`` weight), checked at
save time: the torch actor's actions on a batch of observations drawn from the observation space match the
JAX actor's own within :data:`ACTION_TOLERANCE` (1e-4), or the save fails. Export, evaluation and HIL
therefore meet the same file kind as for a torch run; the JAX checkpoint itself stays in ``checkpoint/`` for
``--resume``.
"""

from __future__ import annotations

import os
from pathlib import Path
from typing import Any

import numpy as np

# One XLA thread: reproducible, and parallel runs do not fight over cores (set before jax is imported).
os.environ.setdefault("XLA_FLAGS", "--xla_cpu_multi_thread_eigen=false intra_op_parallelism_threads=1")

BACKENDS = ("torch", "jax")
"""Where TD3's updates run: SB3's torch, or sbx-rl's JAX."""
ACTION_TOLERANCE = 1e-4
"""The most a converted torch actor's action may differ from the JAX actor's: float32 sums in another order
(XLA's and torch's) over the whole observation box differ by ~1e-5; a wrong layout differs by O(1)."""
CHECK_SAMPLES = 256
"""Observations drawn to check a conversion."""


def jax_td3_class() -> Any:
    """sbx's TD3 class (imported on first use: JAX's import costs seconds)."""
    from sbx import TD3

    return TD3


def build_jax_td3(cfg: Any, env: Any, seed: int, tb: Path | None, noise: Any) -> Any:
    """A fresh sbx TD3 with ``cfg``'s hyperparameters (a :class:`train.config.TD3Config`)."""
    return jax_td3_class()(
        "MlpPolicy",
        env,
        learning_rate=cfg.learning_rate,
        gamma=cfg.gamma,
        batch_size=cfg.batch_size,
        buffer_size=cfg.buffer_size,
        tau=cfg.tau,
        learning_starts=cfg.learning_starts,
        train_freq=cfg.train_freq,
        gradient_steps=cfg.gradient_steps,
        policy_delay=cfg.policy_delay,
        target_policy_noise=cfg.target_policy_noise,
        action_noise=noise,
        policy_kwargs={"net_arch": list(cfg.net_arch)},
        tensorboard_log=str(tb) if tb else None,
        seed=seed,
        verbose=0,
    )


def is_jax_model(model: Any) -> bool:
    """Whether ``model`` is an sbx model (its policy holds Flax parameters)."""
    return hasattr(getattr(model, "policy", None), "actor_state")


def jax_q0(model: Any, obs: np.ndarray) -> float:
    """The smaller of the twin critics' values of ``obs`` and the actor's action there (MATLAB's Q0)."""
    policy = model.policy
    x = np.asarray(obs, dtype=np.float32).reshape(1, -1)
    action = policy.select_action(policy.actor_state, x)
    q = policy.qf.apply(policy.qf_state.params, x, action)
    return float(np.min(np.asarray(q)))


def _dense_layers(params: Any) -> list[tuple[np.ndarray, np.ndarray]]:
    """(kernel, bias) of each ``Dense_k`` in ``params``, in order of k."""
    names = sorted((k for k in params if k.startswith("Dense_")), key=lambda k: int(k.split("_")[1]))
    return [(np.asarray(params[k]["kernel"]), np.asarray(params[k]["bias"])) for k in names]


def _linears(module: Any) -> list[Any]:
    import torch

    return [m for m in module.modules() if isinstance(m, torch.nn.Linear)]


def _copy(layers: list[tuple[np.ndarray, np.ndarray]], linears: list[Any]) -> None:
    import torch

    if len(layers) != len(linears):
        raise ValueError(f"{len(layers)} Flax layers against {len(linears)} torch layers")
    with torch.no_grad():
        for (kernel, bias), linear in zip(layers, linears, strict=True):
            linear.weight.copy_(torch.from_numpy(np.array(kernel.T)))
            linear.bias.copy_(torch.from_numpy(np.array(bias)))


def to_torch_td3(model: Any) -> Any:
    """An SB3 torch TD3 with ``model``'s (sbx TD3) actor and critics, targets included; raises
    ``ValueError`` when the torch actor's actions differ from the JAX actor's by more than
    :data:`ACTION_TOLERANCE`."""
    import torch
    from stable_baselines3 import TD3

    arch = list(model.policy.net_arch_pi)
    critic_arch = list(model.policy.net_arch_qf)
    torch_model = TD3(
        "MlpPolicy",
        model.env,
        policy_kwargs={"net_arch": {"pi": arch, "qf": critic_arch}, "activation_fn": torch.nn.ReLU},
        gamma=model.gamma,
        batch_size=model.batch_size,
        tau=model.tau,
        policy_delay=model.policy_delay,
        target_policy_noise=model.target_policy_noise,
        buffer_size=1,
        device="cpu",
        seed=0,
    )
    policy = torch_model.policy
    actor_state, qf_state = model.policy.actor_state, model.policy.qf_state
    _copy(_dense_layers(actor_state.params["params"]), _linears(policy.actor))
    _copy(_dense_layers(actor_state.target_params["params"]), _linears(policy.actor_target))
    for critic, params in ((policy.critic, qf_state.params), (policy.critic_target, qf_state.target_params)):
        stacked = params["params"]["VmapContinuousCritic_0"]
        for k, q_net in enumerate(critic.q_networks):
            per_critic = {name: {p: v[k] for p, v in layer.items()} for name, layer in stacked.items()}
            _copy(_dense_layers(per_critic), _linears(q_net))
    _check(model, policy)
    torch_model.num_timesteps = model.num_timesteps
    torch_model._n_updates = model._n_updates
    return torch_model


def _check(model: Any, policy: Any) -> None:
    import torch

    space = model.observation_space
    rng = np.random.default_rng(0)
    obs = rng.uniform(space.low, space.high, size=(CHECK_SAMPLES, *space.shape)).astype(np.float32)
    jax_actions = np.asarray(model.policy.select_action(model.policy.actor_state, obs))
    with torch.no_grad():
        torch_actions = policy.actor(torch.from_numpy(obs)).numpy()
    worst = float(np.max(np.abs(jax_actions - torch_actions)))
    if not worst <= ACTION_TOLERANCE:
        raise ValueError(f"the torch actor differs from the JAX actor by {worst:.3g} (> {ACTION_TOLERANCE})")


def save_as_torch(model: Any, path: Path) -> None:
    """Write ``model`` (an sbx TD3) to ``path`` as an SB3 torch TD3 zip (checked: :func:`to_torch_td3`)."""
    to_torch_td3(model).save(path)
