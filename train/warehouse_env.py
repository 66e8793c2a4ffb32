"""``embedrl/WarehouseRobot-v0``: a differential-drive robot drives through a gap between shelves."""

from __future__ import annotations

import math
from typing import Any

import gymnasium as gym
import numpy as np
from gymnasium import spaces

from embedrl.train import layout, rewards
from embedrl.train.rewards import COLLISION_PENALTY, SUCCESS_BONUS
from embedrl.train.robot import SAMPLE_TIME
from embedrl.train.scenarios import STATIC
from embedrl.train.world import ObsBounds, Pose, World, checked_pose, held_action

MAX_EPISODE_STEPS = STATIC.max_steps
reward = rewards.thesis
"""The reference study's reward for one step (:func:`train.rewards.thesis`)."""

__all__ = ["COLLISION_PENALTY", "MAX_EPISODE_STEPS", "SUCCESS_BONUS", "WarehouseRobotEnv", "reward"]


class WarehouseRobotEnv(gym.Env[np.ndarray, np.ndarray]):
    """A differential-drive robot must drive from beside three shelves down through the gap.

    ## Description
    A top-down warehouse (pymunk physics, no gravity, metres and seconds). Two lower shelves
    (0.8 m x 0.15 m) stand on the bottom wall with a 0.6 m gap between them; a third shelf
    (2.2 m x 0.3 m) stands 0.6 m above them; walls close the 3.6 m x 1.45 m arena except
    under the gap. The robot (0.25 m x 0.2 m, 10 kg) starts to the left or the right of the shelves
    and must pass down through the gap without touching a shelf or a wall. The map is in
    :mod:`train.layout`. This adapts the warehouse-robot task of the reference study (docs/environment.md says
    where and why its dimensions differ).

    ## Action Space
    ``Box(-1, 1, (2,), float32)``, held for one sample time (0.3 s):

    | Num | Action                    | Min | Max |
    |-----|---------------------------|-----|-----|
    | 0   | left wheel force ``F_L``  | -1  | 1   |
    | 1   | right wheel force ``F_R`` | -1  | 1   |

    Each wheel pushes ``WHEEL_FORCE_SCALE * F / 2`` newtons along the heading at its own
    position, so the body feels a translational force ``28 N * (F_R + F_L) / 2`` and a
    torque ``28 N * 0.1 m * (F_R - F_L) / 2``. Linear (40 N s/m) and angular (1.4 N m s)
    friction, acting at the wheels, give a top speed of 0.7 m/s and a top turn rate of
    2 rad/s. The wheels do not slip sideways. Actions outside [-1, 1] are clipped.

    ## Observation Space
    ``Box(float32, (6,))``, shelf-aligned coordinates, origin in the middle of the gap at the
    upper edge of the lower shelves. This order is also the input order of exported policies.

    | Num | Observation                        | Min   | Max  | Unit  |
    |-----|------------------------------------|-------|------|-------|
    | 0   | x, position along the shelves      | -1.8  | 1.8  | m     |
    | 1   | y, position across the shelves     | -0.15 | 1.3  | m     |
    | 2   | sin(theta), heading (0 = along +x) | -1    | 1    |       |
    | 3   | cos(theta)                         | -1    | 1    |       |
    | 4   | v, forward speed                   | -0.7  | 0.7  | m/s   |
    | 5   | w, turn rate (counter-clockwise)   | -2.0  | 2.0  | rad/s |

    ## Rewards
    The reference study's reward, on the state after the step:
    ``0.06*exp(-3y) + 0.05*exp(-8x^2) - 0.14 - 0.001*w^2 - 0.01*(F_L^2 + F_R^2)
    + 5*made_it - 2*collided``.
    Before the terminal terms a step earns between -0.164 and +0.004: the -0.14 outweighs
    the shaping almost everywhere the robot can be (y >= -0.15), so short successful episodes
    earn most. A good successful episode (~18 steps) returns ~+3; a collision returns less
    than -2; a timeout about -25. Waiting in the gap earns at most +0.004 per step, far less
    than the +5 for passing through. Range per step: [-2.164, 5.004].
    ``reward="potential-field"`` replaces the position terms by the study's potential field averaged
    over the robot's four corners, with contours around every shelf and wall; ``reward="shaped"`` adds
    potential-based shaping towards the gap to the study's reward (:mod:`train.rewards`).
    ``info["study_return"]`` is the episode's return so far without the shaping term (what the study's
    criterion and every evaluation measure).

    ## Starting State
    Uniformly random: |x| in [1.35, 1.6] m on a random side, y in [0.1, 1.0] m, heading in
    [-pi, pi), at rest. Only ``reset(seed=...)`` seeds it.
    ``reset(options={"start_pose": (x, y, theta)})`` starts from a given pose instead; a pose
    outside the arena or overlapping a shelf or wall raises ``ValueError``.

    ## Episode End
    - Terminated, success: the robot centre passes below y = -0.15 m (through the gap).
    - Terminated, collision: the robot touches a shelf or a wall (``info["collided_with"]``
      names it).
    - Truncated: 200 steps (60 s).

    ``info`` always carries ``is_success``, ``collided`` and ``collided_with`` (or ``None``).

    ## Arguments
    ``gymnasium.make("embedrl/WarehouseRobot-v0", render_mode="rgb_array", reward="thesis",
    success_bonus=5.0)`` (``reward`` is ``"thesis"``, ``"potential-field"`` or ``"shaped"``).

    ## Version History
    - v0: initial version (static scenario).
    """

    SPEC = STATIC
    """The scenario spec: spaces, step limit."""
    metadata = {"render_modes": ["rgb_array"], "render_fps": 1 / SAMPLE_TIME}  # noqa: RUF012 (gymnasium API)

    def __init__(
        self,
        render_mode: str | None = None,
        reward: str = "thesis",
        success_bonus: float = SUCCESS_BONUS,
        shaping_gamma: float = rewards.SHAPING_GAMMA,
        shaping_gain: float = rewards.SHAPING_GAIN,
    ) -> None:
        if render_mode is not None and render_mode not in self.metadata["render_modes"]:
            raise ValueError(
                f"render_mode {render_mode!r} is not supported; use one of {self.metadata['render_modes']}"
            )
        rewards.check_options(reward, success_bonus, shaping_gain)
        self.render_mode = render_mode
        self.reward_name = reward
        self.success_bonus = success_bonus
        self.shaping_gamma = shaping_gamma
        self.shaping_gain = shaping_gain
        self.action_space = spaces.Box(self.SPEC.act_low, self.SPEC.act_high, dtype=np.float32)
        low, high = self.SPEC.obs_low, self.SPEC.obs_high
        self.observation_space = spaces.Box(low, high, dtype=np.float32)
        self._low, self._high = low, high
        self._bounds = ObsBounds(low, high)
        self._world: World | None = None
        self._phi = 0.0
        """The shaping potential of the state before the step (``reward="shaped"``)."""
        self._study_return = 0.0
        """The episode's return so far without the shaping term (``info["study_return"]``)."""
        self._steps = 0
        self.trajectory: list[tuple[float, float, float]] = []
        """(x, y, theta) after reset and after every step of the current episode."""
        self.obstacle_history: list[tuple[layout.Rect, ...]] = []
        """The moving obstacles after reset and after every step (empty tuples in the static scenario)."""

    def _observe(self) -> np.ndarray:
        assert self._world is not None
        # A contact impulse in the last physics step can push v or w past their bounds.
        return self._bounds.clip(self._world.robot_state(0))

    # -- gymnasium API -----------------------------------------------------------------------

    def reset(
        self, *, seed: int | None = None, options: dict[str, Any] | None = None
    ) -> tuple[np.ndarray, dict[str, Any]]:
        super().reset(seed=seed)
        unknown = set(options or {}) - set(self._RESET_OPTIONS)
        if unknown:
            raise ValueError(
                f"unknown reset option(s) {sorted(unknown)}; supported: {sorted(self._RESET_OPTIONS)}"
            )
        options = options or {}
        if options.get("start_pose") is not None:
            x, y, theta = checked_pose(options["start_pose"])
        else:
            side = 1.0 if self.np_random.random() < 0.5 else -1.0
            x = side * self.np_random.uniform(layout.START_X_MIN, layout.START_X_MAX)
            y = self.np_random.uniform(layout.START_Y_MIN, layout.START_Y_MAX)
            theta = self.np_random.uniform(-math.pi, math.pi)
        world = self._make_world((x, y, theta), options)
        overlaps = world.overlaps(0)
        if overlaps:
            self._world = None
            raise ValueError(f"start_pose ({x}, {y}, {theta}) overlaps {', '.join(overlaps)}")
        self._world = world
        self._steps = 0
        self._phi = rewards.potential(x, y, self.shaping_gain)
        self._study_return = 0.0
        self.trajectory = [(x, y, theta)]
        self.obstacle_history = [self._moving_obstacles()]
        return self._observe(), {"is_success": False, "collided": False, "collided_with": None}

    # -- what a scenario changes -----------------------------------------------------------------

    _RESET_OPTIONS: tuple[str, ...] = ("start_pose",)

    def _make_world(self, pose: Pose, options: dict[str, Any]) -> World:
        """The world of a new episode with the robot at ``pose``."""
        if self._world is None:
            return World([pose])
        self._world.reset([pose])
        return self._world

    def _obstacles(self) -> tuple[layout.Rect, ...]:
        """Every obstacle where it is now (the potential-field reward's contours)."""
        return layout.OBSTACLES

    def _moving_obstacles(self) -> tuple[layout.Rect, ...]:
        """Obstacles that move, where they are now (drawn by the renderers)."""
        return ()

    def step(self, action: np.ndarray) -> tuple[np.ndarray, float, bool, bool, dict[str, Any]]:
        if self._world is None:
            raise RuntimeError("call reset() before step()")
        a = held_action(action)
        world = self._world
        world.hold([a])
        made_it = world.drive_one(layout.GOAL_Y)
        self._steps += 1
        hit = world.hits[0]
        collided = hit is not None
        made_it = made_it and not collided
        obs = self._observe()
        pose = world.pose(0)
        self.trajectory.append(pose)
        self.obstacle_history.append(self._moving_obstacles())
        terminated = made_it or collided
        if self.reward_name in ("thesis", "shaped"):
            x, y, w = float(obs[0]), float(obs[1]), float(obs[5])
            r = rewards.thesis(x, y, w, a, made_it, collided, self.success_bonus)
            self._study_return += r
            if self.reward_name == "shaped":
                phi = rewards.potential(pose[0], pose[1], self.shaping_gain)
                r += rewards.shaping(self._phi, phi, terminated, self.shaping_gamma)
                self._phi = phi
        else:
            r = rewards.potential_field(
                pose, float(obs[5]), a, made_it, collided, self._obstacles(), bonus=self.success_bonus
            )
            self._study_return += r
        truncated = not terminated and self._steps >= self.SPEC.max_steps
        info = {
            "is_success": made_it,
            "collided": collided,
            "collided_with": hit,
            "study_return": self._study_return,
        }
        return obs, r, terminated, truncated, info

    def render(self) -> np.ndarray | None:
        if self.render_mode is None:
            gym.logger.warn("render() called without render_mode; use render_mode='rgb_array'")
            return None
        from embedrl.train.rendering import draw_frame

        return draw_frame(self.trajectory, self.obstacle_history[-1] if self.obstacle_history else ())

    def close(self) -> None:
        self._world = None
