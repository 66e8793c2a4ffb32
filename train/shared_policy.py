"""Parameter sharing: a PettingZoo Parallel env seen by Stable-Baselines3 as a vector env, one slot per agent.

One policy acts for every robot and learns from all their transitions, so one network is deployed to
identical nodes. This is SuperSuit's ``black_death`` + ``pettingzoo_env_to_vec_env`` scheme; SuperSuit
3.11's Stable-Baselines3 wrapper does not run with Stable-Baselines3 2.9 (its vector env has no
``seed()``), hence this adapter.

Each slot's episode is its agent's episode: the slot reports ``done`` (with ``terminal_observation``,
``TimeLimit.truncated`` for a truncated agent and Monitor's ``episode`` statistics) at the step its agent
finishes. Until the whole episode ends, a finished agent's slot then stands still in an absorbing state
(zero observation, zero reward, its actions ignored) whose pseudo-episode ends, as a termination without
statistics, when the last agent finishes; then the env resets and every slot starts a real episode.
"""

from __future__ import annotations

import time
from collections.abc import Sequence
from typing import Any

import numpy as np
from pettingzoo import ParallelEnv
from stable_baselines3.common.vec_env.base_vec_env import VecEnv, VecEnvIndices, VecEnvObs, VecEnvStepReturn


class SharedPolicyVecEnv(VecEnv):
    """``env``'s agents as the slots of a vector env (every agent with the same Box spaces)."""

    def __init__(self, env: ParallelEnv) -> None:
        self.env = env
        self.names = list(env.possible_agents)
        first = self.names[0]
        super().__init__(len(self.names), env.observation_space(first), env.action_space(first))
        shape = self.observation_space.shape
        assert shape is not None
        self._zero = np.zeros(shape, dtype=np.float32)
        self._actions: np.ndarray | None = None
        self._returns = np.zeros(self.num_envs)
        self._lengths = np.zeros(self.num_envs, dtype=int)
        self._finished = [False] * self.num_envs
        self._started = time.time()

    def _start(self) -> np.ndarray:
        seed = self._seeds[0] if self._seeds else None
        obs, _ = self.env.reset(seed=seed)
        self._reset_seeds()
        self._returns[:] = 0.0
        self._lengths[:] = 0
        self._finished = [False] * self.num_envs
        return np.stack([obs[a] for a in self.names])

    def reset(self) -> VecEnvObs:
        return self._start()

    def step_async(self, actions: np.ndarray) -> None:
        self._actions = actions

    def step_wait(self) -> VecEnvStepReturn:
        assert self._actions is not None
        acting = set(self.env.agents)
        obs, rewards, terms, truncs, infos = self.env.step(
            {a: self._actions[i] for i, a in enumerate(self.names) if a in acting}
        )
        out_obs = np.zeros((self.num_envs, self._zero.size), dtype=np.float32)
        out_rew = np.zeros(self.num_envs, dtype=np.float32)
        dones = np.zeros(self.num_envs, dtype=bool)
        out_infos: list[dict[str, Any]] = [{} for _ in self.names]
        episode_over = not self.env.agents
        for i, agent in enumerate(self.names):
            if agent in acting:
                out_obs[i] = obs[agent]
                out_rew[i] = rewards[agent]
                self._returns[i] += rewards[agent]
                self._lengths[i] += 1
                out_infos[i] = dict(infos[agent])
                if terms[agent] or truncs[agent]:
                    dones[i] = True
                    self._finished[i] = True
                    out_infos[i]["terminal_observation"] = obs[agent]
                    out_infos[i]["TimeLimit.truncated"] = bool(truncs[agent] and not terms[agent])
                    out_infos[i]["episode"] = {
                        "r": float(self._returns[i]),
                        "l": int(self._lengths[i]),
                        "t": round(time.time() - self._started, 6),
                    }
                    out_obs[i] = self._zero
            elif episode_over:  # the absorbing state's pseudo-episode ends with the real one
                dones[i] = True
                out_infos[i] = {"terminal_observation": self._zero, "TimeLimit.truncated": False}
        if episode_over:
            out_obs = self._start()
        return out_obs, out_rew, dones, out_infos

    def close(self) -> None:
        self.env.close()

    # -- VecEnv plumbing: one underlying env serves every slot -----------------------------------

    def get_attr(self, attr_name: str, indices: VecEnvIndices = None) -> list[Any]:
        return [getattr(self.env, attr_name) for _ in self._indices(indices)]

    def set_attr(self, attr_name: str, value: Any, indices: VecEnvIndices = None) -> None:
        setattr(self.env, attr_name, value)

    def env_method(
        self, method_name: str, *method_args: Any, indices: VecEnvIndices = None, **method_kwargs: Any
    ) -> list[Any]:
        return [getattr(self.env, method_name)(*method_args, **method_kwargs) for _ in self._indices(indices)]

    def env_is_wrapped(self, wrapper_class: type, indices: VecEnvIndices = None) -> list[bool]:
        return [False for _ in self._indices(indices)]

    def _indices(self, indices: VecEnvIndices) -> Sequence[int]:
        if indices is None:
            return range(self.num_envs)
        return [indices] if isinstance(indices, int) else list(indices)
