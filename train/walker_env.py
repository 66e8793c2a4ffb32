"""``embedrl/DeckWalker-v0``: the slide deck's walking robot, gymnasium's MuJoCo Walker2d-v5 with the deck's
reward."""

from __future__ import annotations

import os
from typing import Any

import gymnasium as gym
import numpy as np
from gymnasium import spaces

from embedrl.train import deck_reward
from embedrl.train.deck_reward import TERMS
from embedrl.train.scenarios import WALKER, WALKER_FRAME_SKIP

LATERAL_DEVIATION = 0.0
"""``y`` of the deck's path term: the planar walker cannot leave its line."""
SUCCESS_DISTANCE = 1.0
"""An episode succeeds when the walker is still up at the step limit and has walked at least this far [m]."""
EPISODE_S = WALKER.max_steps * WALKER.sample_time_s
"""``Tf``, the episode length of the deck's survive bonus: 1,000 steps of 8 ms, 8 s."""
FALL = "ground (fell)"
"""``info["collided_with"]`` of a fall: the evaluation reports count falls as collisions."""
HEADLESS_GL = "egl"
"""The OpenGL backend ``render()`` asks MuJoCo for when there is no display and ``MUJOCO_GL`` is not set."""
EPISODE_KEYS = (*(f"episode_{term}" for term in TERMS), "distance")
"""What ``info`` sums over the episode so far (each reward term) and the distance walked: SB3's ``Monitor``
records them at the end of an episode (``info_keywords``)."""


class DeckWalkerEnv(gym.Env[np.ndarray, np.ndarray]):
    """A planar biped (gymnasium's MuJoCo Walker2d-v5) must walk forward without falling.

    ## Description
    Gymnasium's ``Walker2dEnv`` (``walker2d_v5.xml``, 0.002 s physics steps, 4 per control step) drives the
    physics, its start, its fall test and its observation; this env replaces its reward by the slide deck's
    (:mod:`train.deck_reward`), bounds its observation and logs each reward term.

    ## Action Space
    ``Box(-1, 1, (6,), float32)``, held for one sample time (0.008 s); each is a motor torque in units of the
    model's gear, 100 N m (the safe action is no torque). Actions outside [-1, 1] are clipped; a non-finite
    action is a ``ValueError``.

    | Num | Action                          | Min | Max |
    |-----|---------------------------------|-----|-----|
    | 0   | right thigh motor torque        | -1  | 1   |
    | 1   | right knee motor torque         | -1  | 1   |
    | 2   | right foot motor torque         | -1  | 1   |
    | 3   | left thigh motor torque         | -1  | 1   |
    | 4   | left knee motor torque          | -1  | 1   |
    | 5   | left foot motor torque          | -1  | 1   |

    ## Observation Space
    ``Box(float32, (17,))``: Walker2d-v5's observation (Walker2d-v5 clips the velocities to +-10), clipped to
    the ranges of the scenario spec (:data:`train.scenarios.WALKER`; a joint's range is its limits with at
    least 0.5 rad to spare, MuJoCo's limits being soft). This order is also the input order of exported
    policies.

    | Num | Observation               | Min  | Max | Unit  |
    |-----|---------------------------|------|-----|-------|
    | 0   | trunk height              | 0    | 2.5 | m     |
    | 1   | trunk pitch (0 = upright) | -2   | 2   | rad   |
    | 2   | right thigh joint angle   | -3.2 | 0.6 | rad   |
    | 3   | right knee joint angle    | -3.2 | 0.6 | rad   |
    | 4   | right foot joint angle    | -1.3 | 1.3 | rad   |
    | 5   | left thigh joint angle    | -3.2 | 0.6 | rad   |
    | 6   | left knee joint angle     | -3.2 | 0.6 | rad   |
    | 7   | left foot joint angle     | -1.3 | 1.3 | rad   |
    | 8   | trunk forward velocity    | -10  | 10  | m/s   |
    | 9   | trunk vertical velocity   | -10  | 10  | m/s   |
    | 10  | trunk pitch rate          | -10  | 10  | rad/s |
    | 11  | right thigh joint rate    | -10  | 10  | rad/s |
    | 12  | right knee joint rate     | -10  | 10  | rad/s |
    | 13  | right foot joint rate     | -10  | 10  | rad/s |
    | 14  | left thigh joint rate     | -10  | 10  | rad/s |
    | 15  | left knee joint rate      | -10  | 10  | rad/s |
    | 16  | left foot joint rate      | -10  | 10  | rad/s |

    ## Rewards
    The deck's ``r_t = v_x - 3 y^2 - 50 z_hat^2 + 25 Ts/Tf - 0.02 sum_i (u_{t-1}^i)^2``: ``v_x`` the trunk's
    forward velocity over the step (Walker2d-v5's ``x_velocity``); ``y = 0`` (the walker is planar: the path
    term is identically zero); ``z_hat`` the trunk height minus its height after reset; the survive bonus
    ``25 * 0.008 / 8 = 0.025`` on every step that ends upright; the effort on the previous step's action
    (zero on the first step). ``reward=`` picks one of the deck's shaping stages
    (:data:`train.deck_reward.VARIANTS`). ``info`` carries each term of the step (``reward_<term>``), their
    sums over the episode so far (``episode_<term>``), the return so far (``study_return``), ``x_position``,
    ``x_velocity`` and the ``distance`` walked since reset.

    ## Starting State
    Walker2d-v5's: standing at 1.25 m, every position and velocity perturbed by U(-0.005, 0.005). Only
    ``reset(seed=...)`` seeds it.

    ## Episode End
    - Terminated, fall: Walker2d-v5's unhealthy test (trunk height outside (0.8, 2) m or pitch outside
      (-1, 1) rad); ``info["collided"]`` is true and ``info["collided_with"]`` says ``ground (fell)``.
    - Truncated: 1000 steps (8 s). ``info["is_success"]``: truncated upright after walking at least 1 m.

    ## Arguments
    ``gymnasium.make("embedrl/DeckWalker-v0", render_mode="rgb_array", reward="deck")`` (``reward`` is one of
    ``velocity``, ``upright``, ``effort``, ``deck``). Without a display and without ``MUJOCO_GL``,
    ``render()`` uses EGL.

    ## Version History
    - v0: initial version.
    """

    SPEC = WALKER
    """The scenario spec: spaces, sample time, step limit."""
    EPISODE_KEYS = EPISODE_KEYS
    """The ``info`` keys a training run logs per episode (:data:`EPISODE_KEYS`)."""
    metadata = {"render_modes": ["rgb_array"], "render_fps": round(1 / WALKER.sample_time_s)}  # noqa: RUF012

    def __init__(self, render_mode: str | None = None, reward: str = deck_reward.DEFAULT_VARIANT) -> None:
        if render_mode is not None and render_mode not in self.metadata["render_modes"]:
            raise ValueError(
                f"render_mode {render_mode!r} is not supported; use one of {self.metadata['render_modes']}"
            )
        self.reward_config = deck_reward.variant(reward)
        self.reward_name = reward
        self.render_mode = render_mode
        self.action_space = spaces.Box(self.SPEC.act_low, self.SPEC.act_high, dtype=np.float32)
        self.observation_space = spaces.Box(self.SPEC.obs_low, self.SPEC.obs_high, dtype=np.float32)
        self._obs_low, self._obs_high = self.SPEC.obs_low, self.SPEC.obs_high
        self._act_low, self._act_high = self.SPEC.act_low, self.SPEC.act_high
        self._sim = _simulation(render_mode)
        self._started = False
        self._steps = 0
        self._start_x = self._start_z = 0.0
        self._previous_action = np.zeros(len(self.SPEC.action), dtype=np.float32)
        self._sums = dict.fromkeys(TERMS, 0.0)
        self.joint_trajectory: list[tuple[float, ...]] = []
        """MuJoCo's positions (``qpos``: x, height, pitch, the six joint angles) after reset and after every
        step of the episode: what :func:`render_joint_trajectory` draws again (a HIL run's walk)."""

    def _observe(self, raw: np.ndarray) -> np.ndarray:
        obs = np.clip(np.asarray(raw, dtype=np.float32), self._obs_low, self._obs_high)
        return np.asarray(obs, dtype=np.float32)

    def reset(
        self, *, seed: int | None = None, options: dict[str, Any] | None = None
    ) -> tuple[np.ndarray, dict[str, Any]]:
        super().reset(seed=seed)
        if options:
            raise ValueError(f"unknown reset option(s) {sorted(options)}; this env takes none")
        raw, _ = self._sim.reset(seed=int(self.np_random.integers(2**31)))
        qpos = self._sim.unwrapped.data.qpos  # type: ignore[attr-defined]
        self._start_x, self._start_z = float(qpos[0]), float(qpos[1])
        self._started, self._steps = True, 0
        self._previous_action = np.zeros(len(self.SPEC.action), dtype=np.float32)
        self._sums = dict.fromkeys(TERMS, 0.0)
        self.joint_trajectory = [_positions(qpos)]
        return self._observe(raw), self._info(dict.fromkeys(TERMS, 0.0), 0.0, False, False)

    def step(self, action: np.ndarray) -> tuple[np.ndarray, float, bool, bool, dict[str, Any]]:
        if not self._started:
            raise RuntimeError("call reset() before step()")
        a = np.asarray(action, dtype=np.float32).reshape(-1)
        if a.shape != self._act_low.shape or not np.all(np.isfinite(a)):
            raise ValueError(f"the action must be {len(self.SPEC.action)} finite numbers, got {action!r}")
        a = np.clip(a, self._act_low, self._act_high)
        raw, _, fell, _, sim_info = self._sim.step(a)
        self._steps += 1
        self.joint_trajectory.append(_positions(self._sim.unwrapped.data.qpos))  # type: ignore[attr-defined]
        z_hat = float(self._sim.unwrapped.data.qpos[1]) - self._start_z  # type: ignore[attr-defined]
        terms = self.reward_config.terms(
            sim_info["x_velocity"], LATERAL_DEVIATION, z_hat, self._previous_action, self.SPEC.sample_time_s,
            EPISODE_S,
        )  # fmt: skip
        if fell:
            terms["survive"] = 0.0
        self._previous_action = a
        for term, value in terms.items():
            self._sums[term] += value
        truncated = not fell and self._steps >= self.SPEC.max_steps
        info = self._info(terms, float(sim_info["x_velocity"]), bool(fell), truncated)
        return self._observe(raw), float(sum(terms.values())), bool(fell), truncated, info

    def _info(self, terms: dict[str, float], v_x: float, fell: bool, truncated: bool) -> dict[str, Any]:
        x = float(self._sim.unwrapped.data.qpos[0])  # type: ignore[attr-defined]
        distance = x - self._start_x
        return {
            "is_success": truncated and distance >= SUCCESS_DISTANCE,
            "collided": fell,
            "collided_with": FALL if fell else None,
            "x_position": x,
            "x_velocity": v_x,
            "distance": distance,
            "study_return": float(sum(self._sums.values())),
            **{f"reward_{term}": value for term, value in terms.items()},
            **{f"episode_{term}": value for term, value in self._sums.items()},
        }

    def render(self) -> np.ndarray | None:
        if self.render_mode is None:
            gym.logger.warn("render() called without render_mode; use render_mode='rgb_array'")
            return None
        if "MUJOCO_GL" not in os.environ and not os.environ.get("DISPLAY"):
            os.environ["MUJOCO_GL"] = HEADLESS_GL  # without a display MuJoCo's default (GLFW) cannot render
        follow_trunk(self._sim)
        frame = self._sim.render()
        return None if frame is None else np.asarray(frame)

    def close(self) -> None:
        self._sim.close()

    # -- pickling: a training checkpoint saves the env mid-episode -------------------------------------

    def __getstate__(self) -> dict[str, Any]:
        state = {k: v for k, v in self.__dict__.items() if k != "_sim"}
        data = self._sim.unwrapped.data  # type: ignore[attr-defined]
        state["_physics"] = {
            name: np.copy(getattr(data, name)) for name in ("qpos", "qvel", "act", "ctrl", "qacc_warmstart")
        }
        state["_physics_time"] = float(data.time)
        return state

    def __setstate__(self, state: dict[str, Any]) -> None:
        physics, time = state.pop("_physics"), state.pop("_physics_time")
        self.__dict__.update(state)
        self._sim = _simulation(self.render_mode)
        self._sim.reset(seed=0)
        data = self._sim.unwrapped.data  # type: ignore[attr-defined]
        for name, value in physics.items():
            getattr(data, name)[:] = value
        data.time = time


def _simulation(render_mode: str | None) -> gym.Env[np.ndarray, np.ndarray]:
    """Gymnasium's Walker2d-v5 itself, without the wrappers of ``gym.make`` (this env keeps the time)."""
    from gymnasium.envs.mujoco.walker2d_v5 import Walker2dEnv

    return Walker2dEnv(render_mode=render_mode, frame_skip=WALKER_FRAME_SKIP)


def _positions(qpos: np.ndarray) -> tuple[float, ...]:
    return tuple(float(q) for q in qpos)


CAMERA_DISTANCE = 3.0
"""The camera's distance from the point it looks at [m] (Walker2d-v5's is 4)."""


def follow_trunk(sim: gym.Env[np.ndarray, np.ndarray]) -> None:
    """Point Walker2d-v5's camera at the trunk's forward position: gymnasium's renderer leaves its camera
    free (its ``trackbodyid`` does not track), so a walker would leave the picture."""
    renderer = sim.unwrapped.mujoco_renderer  # type: ignore[attr-defined]
    camera = renderer._get_viewer(render_mode="rgb_array").cam
    camera.distance = CAMERA_DISTANCE
    camera.lookat[0] = float(sim.unwrapped.data.qpos[0])  # type: ignore[attr-defined]


WALK_FRAME_STRIDE = 8
"""Steps per frame of a replayed walk: 8 x 8 ms, 64 ms a frame (about 16 frames per second: a small file)."""
WALK_FRAME_PX = 320
"""Width and height of a replayed walk's frames in pixels."""


def walk_frame_steps(steps: int) -> list[int]:
    """The steps of an episode of ``steps`` steps a replay draws: every :data:`WALK_FRAME_STRIDE`-th from the
    reset (step 0) and the last one (where the episode ended)."""
    picks = list(range(0, steps + 1, WALK_FRAME_STRIDE))
    return picks if picks[-1] == steps else [*picks, steps]


def render_joint_trajectory(joint_trajectory: list[tuple[float, ...]]) -> list[np.ndarray]:
    """The frames of an episode drawn again from its recorded positions
    (:attr:`DeckWalkerEnv.joint_trajectory`) by MuJoCo's renderer, at the steps :func:`walk_frame_steps`
    picks, the camera following the trunk.
    ValueError if a row is not one of the model's position vectors."""
    from gymnasium.envs.mujoco.walker2d_v5 import Walker2dEnv

    if "MUJOCO_GL" not in os.environ and not os.environ.get("DISPLAY"):
        os.environ["MUJOCO_GL"] = HEADLESS_GL
    import mujoco  # type: ignore[import-untyped]

    sim: gym.Env[np.ndarray, np.ndarray] = Walker2dEnv(
        render_mode="rgb_array", width=WALK_FRAME_PX, height=WALK_FRAME_PX
    )
    try:
        sim.reset(seed=0)
        model, data = sim.unwrapped.model, sim.unwrapped.data  # type: ignore[attr-defined]
        frames = []
        for step in walk_frame_steps(len(joint_trajectory) - 1):
            qpos = np.asarray(joint_trajectory[step], dtype=np.float64)
            if qpos.shape != data.qpos.shape or not np.all(np.isfinite(qpos)):
                raise ValueError(f"step {step} of the walk is not {data.qpos.size} finite positions")
            data.qpos[:] = qpos
            data.qvel[:] = 0.0
            mujoco.mj_forward(model, data)
            follow_trunk(sim)
            frames.append(np.asarray(sim.render()))
        return frames
    finally:
        sim.close()
