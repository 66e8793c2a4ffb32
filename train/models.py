"""Trained Stable-Baselines3 models as policies: the policy network, and its normalisation statistics.

Loading a model is a training concept: evaluation uses it here, and the exporter builds its ONNX graph
from the :class:`LoadedPolicy` this module returns.
"""

from __future__ import annotations

import pickle
import zipfile
from dataclasses import dataclass
from pathlib import Path
from typing import Any

import numpy as np
from gymnasium import spaces
from stable_baselines3.common.policies import ActorCriticPolicy, BasePolicy
from stable_baselines3.common.save_util import load_from_zip_file
from stable_baselines3.sac.policies import SACPolicy
from stable_baselines3.td3.policies import TD3Policy

from embedrl.train.errors import InvalidModelFileError, UnsupportedModelFileError

VECNORMALIZE_FILE = "vecnormalize.pkl"
"""Statistics next to a model with this name are used unless told otherwise."""


def vecnormalize_beside(model: Path) -> Path | None:
    """``<model>_vecnormalize.pkl`` (shipped policies share a folder), else ``vecnormalize.pkl`` (a run)."""
    for candidate in (model.with_name(f"{model.stem}_{VECNORMALIZE_FILE}"), model.parent / VECNORMALIZE_FILE):
        if candidate.is_file():
            return candidate
    return None


@dataclass(frozen=True)
class ObsNormalization:
    """VecNormalize's observation transform: ``clip((obs - mean) / sqrt(var + eps), -clip, clip)``."""

    mean: np.ndarray
    var: np.ndarray
    epsilon: float
    clip: float

    def apply(self, obs: np.ndarray) -> np.ndarray:
        """Exactly what VecNormalize.normalize_obs computes (float64), as float32."""
        out = np.clip((obs - self.mean) / np.sqrt(self.var + self.epsilon), -self.clip, self.clip)
        return np.asarray(out, dtype=np.float32)


@dataclass(frozen=True)
class LoadedPolicy:
    """An SB3 policy ready for export and for reference predictions."""

    policy: BasePolicy
    observation_space: spaces.Box
    action_space: spaces.Box
    normalization: ObsNormalization | None

    @property
    def kind(self) -> str:
        return type(self.policy).__name__

    def predict(self, obs: np.ndarray) -> np.ndarray:
        """``predict(deterministic=True)`` on a batch of raw observations, normalised as in training."""
        x = obs if self.normalization is None else self.normalization.apply(obs)
        actions, _ = self.policy.predict(x, deterministic=True)
        return np.asarray(actions, dtype=np.float32)


def load_sb3(path: Path, vecnormalize: Path | None = None) -> LoadedPolicy:
    """Load the policy of an SB3 ``.zip`` (any algorithm) without its algorithm or environment."""
    if not path.is_file():
        raise InvalidModelFileError(f"{path}: no such file")
    try:
        data, params, _ = load_from_zip_file(path, device="cpu", print_system_info=False)
    except (zipfile.BadZipFile, KeyError, ValueError, EOFError, RuntimeError, pickle.UnpicklingError) as exc:
        raise InvalidModelFileError(f"{path}: not a readable Stable-Baselines3 model ({exc})") from None
    if data is None or params is None or "policy" not in params:
        raise InvalidModelFileError(f"{path}: the archive has no policy parameters")
    cls = data.get("policy_class")
    if not isinstance(cls, type) or not issubclass(cls, (TD3Policy, SACPolicy, ActorCriticPolicy)):
        name = getattr(cls, "__name__", repr(cls))
        raise UnsupportedModelFileError(
            f"{path}: policy class {name} is not supported; supported: TD3Policy (TD3, DDPG), "
            "SACPolicy (SAC), ActorCriticPolicy (PPO, A2C)"
        )
    obs_space, act_space = data.get("observation_space"), data.get("action_space")
    for role, space in (("observation", obs_space), ("action", act_space)):
        if not isinstance(space, spaces.Box) or len(space.shape) != 1:
            raise UnsupportedModelFileError(f"{path}: {role} space {space} is not supported; need a 1-D Box")
    assert isinstance(obs_space, spaces.Box) and isinstance(act_space, spaces.Box)
    kwargs = dict(data.get("policy_kwargs", {}))
    if data.get("use_sde") or kwargs.get("use_sde"):
        raise UnsupportedModelFileError(f"{path}: policies with gSDE (use_sde=True) are not supported")
    policy = cls(obs_space, act_space, lambda _: 0.0, **kwargs)
    try:
        policy.load_state_dict(params["policy"])  # type: ignore[arg-type]
    except RuntimeError as exc:
        raise InvalidModelFileError(f"{path}: policy parameters do not match the policy ({exc})") from None
    policy.set_training_mode(False)
    normalization = _load_vecnormalize(vecnormalize, obs_space) if vecnormalize else None
    return LoadedPolicy(policy, obs_space, act_space, normalization)


def _load_vecnormalize(path: Path, obs_space: spaces.Box) -> ObsNormalization | None:
    if not path.is_file():
        raise InvalidModelFileError(f"{path}: no such file (VecNormalize statistics)")
    try:
        with path.open("rb") as f:
            stats: Any = pickle.load(f)
        rms, enabled = stats.obs_rms, bool(stats.norm_obs)
        mean, var = np.asarray(rms.mean, np.float64), np.asarray(rms.var, np.float64)
        epsilon, clip = float(stats.epsilon), float(stats.clip_obs)
    except (pickle.UnpicklingError, EOFError, AttributeError, ValueError, TypeError) as exc:
        raise InvalidModelFileError(f"{path}: not VecNormalize statistics saved by SB3 ({exc})") from None
    if not enabled:
        return None
    if mean.shape != obs_space.shape or var.shape != obs_space.shape:
        raise InvalidModelFileError(
            f"{path}: statistics of shape {mean.shape} do not fit observations {obs_space.shape}"
        )
    return ObsNormalization(mean, var, epsilon, clip)
