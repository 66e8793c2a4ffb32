"""``embedrl/WarehouseRobot-v0``: a differential-drive robot drives through a gap between shelves."""

from __future__ import annotations

import math
from typing import Any

import gymnasium as gym
import numpy as np
import pymunk
from gymnasium import spaces

from embedrl.train import layout
from embedrl.train.robot import (
    ANGULAR_FRICTION,
    LINEAR_FRICTION,
    PHYSICS_SUBSTEPS,
    ROBOT_LENGTH,
    ROBOT_MASS,
    ROBOT_WIDTH,
    SAMPLE_TIME,
    WHEEL_FORCE_SCALE,
    WHEEL_HALF_TRACK,
)
from embedrl.train.scenarios import STATIC

MAX_EPISODE_STEPS = STATIC.max_steps

SUCCESS_BONUS = 5.0
COLLISION_PENALTY = 2.0

_ROBOT = 1
_OBSTACLE = 2


def reward(x: float, y: float, w: float, action: np.ndarray, made_it: bool, collided: bool) -> float:
    """The reference study's reward for one step, evaluated on the state after the step."""
    return float(
        0.06 * math.exp(-3.0 * y)
        + 0.05 * math.exp(-8.0 * x * x)
        - 0.14
        - 0.001 * w * w
        - 0.01 * float(action[0] ** 2 + action[1] ** 2)
        + SUCCESS_BONUS * made_it
        - COLLISION_PENALTY * collided
    )


class WarehouseRobotEnv(gym.Env[np.ndarray, np.ndarray]):
    """A differential-drive robot must drive from beside three shelves down through the gap.

    ## Description
    A top-down warehouse (pymunk physics, no gravity, metres and seconds). Two lower shelves
    (0.8 m x 0.15 m) stand on the bottom wall with a 0.6 m gap between them; a third shelf
    (2.2 m x 0.3 m) stands 0.6 m above them; walls close the 3.6 m x 1.45 m arena except
    under the gap. The robot (0.25 m x 0.2 m, 10 kg) starts to the left or the right of the shelves
    and must pass down through the gap without touching a shelf or a wall. The map is in
    :mod:`train.layout`. This reproduces the warehouse-robot task of the reference study.

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
    ``gymnasium.make("embedrl/WarehouseRobot-v0", render_mode="rgb_array")``

    ## Version History
    - v0: initial version (static scenario).
    """

    metadata = {"render_modes": ["rgb_array"], "render_fps": 1 / SAMPLE_TIME}  # noqa: RUF012 (gymnasium API)

    def __init__(self, render_mode: str | None = None) -> None:
        if render_mode is not None and render_mode not in self.metadata["render_modes"]:
            raise ValueError(
                f"render_mode {render_mode!r} is not supported; use one of {self.metadata['render_modes']}"
            )
        self.render_mode = render_mode
        self.action_space = spaces.Box(STATIC.act_low, STATIC.act_high, dtype=np.float32)
        low, high = STATIC.obs_low, STATIC.obs_high
        self.observation_space = spaces.Box(low, high, dtype=np.float32)
        self._low, self._high = low, high
        self._space: pymunk.Space | None = None
        self._robot: pymunk.Body | None = None
        self._hit: str | None = None
        self._names: dict[pymunk.Shape, str] = {}
        self._steps = 0
        self.trajectory: list[tuple[float, float, float]] = []
        """(x, y, theta) after reset and after every step of the current episode."""

    # -- physics -----------------------------------------------------------------------------

    def _build_space(self, x: float, y: float, theta: float) -> None:
        """Build a fresh space: rebuilding (not restoring) keeps same-seed runs bit-identical."""
        space = pymunk.Space()
        robot = pymunk.Body(ROBOT_MASS, pymunk.moment_for_box(ROBOT_MASS, (ROBOT_LENGTH, ROBOT_WIDTH)))
        robot.position = (x, y)
        robot.angle = theta
        body_shape = pymunk.Poly.create_box(robot, (ROBOT_LENGTH, ROBOT_WIDTH))
        body_shape.collision_type = _ROBOT
        space.add(robot, body_shape)
        self._names = {}
        for rect in layout.OBSTACLES:
            shape = pymunk.Poly(space.static_body, list(rect.corners))
            shape.collision_type = _OBSTACLE
            space.add(shape)
            self._names[shape] = rect.name
        space.on_collision(_ROBOT, _OBSTACLE, begin=self._on_contact)
        self._space, self._robot, self._hit = space, robot, None

    def _on_contact(self, arbiter: pymunk.Arbiter, space: pymunk.Space, data: Any) -> None:
        if self._hit is None:
            a, b = arbiter.shapes
            self._hit = self._names.get(b, self._names.get(a, "obstacle"))

    @staticmethod
    def _checked_pose(pose: Any) -> tuple[float, float, float]:
        try:
            x, y, theta = (float(p) for p in pose)
        except (TypeError, ValueError):
            raise ValueError(f"start_pose must be three numbers (x, y, theta), got {pose!r}") from None
        if not all(math.isfinite(p) for p in (x, y, theta)):
            raise ValueError(f"start_pose must be finite, got {pose!r}")
        if not (abs(x) < layout.ARENA_HALF_WIDTH and layout.GOAL_Y < y < layout.ARENA_TOP):
            raise ValueError(
                f"start_pose ({x}, {y}) is outside the arena: |x| < {layout.ARENA_HALF_WIDTH}, "
                f"{layout.GOAL_Y} < y < {layout.ARENA_TOP}"
            )
        return x, y, theta

    def _observe(self) -> np.ndarray:
        assert self._robot is not None
        r = self._robot
        c, s = math.cos(r.angle), math.sin(r.angle)
        v = r.velocity.x * c + r.velocity.y * s
        obs = np.array([r.position.x, r.position.y, s, c, v, r.angular_velocity], dtype=np.float32)
        # A contact impulse in the last physics step can push v or w past their bounds.
        return np.clip(obs, self._low, self._high)

    # -- gymnasium API -----------------------------------------------------------------------

    def reset(
        self, *, seed: int | None = None, options: dict[str, Any] | None = None
    ) -> tuple[np.ndarray, dict[str, Any]]:
        super().reset(seed=seed)
        unknown = set(options or {}) - {"start_pose"}
        if unknown:
            raise ValueError(f"unknown reset option(s) {sorted(unknown)}; supported: ['start_pose']")
        if options and options.get("start_pose") is not None:
            x, y, theta = self._checked_pose(options["start_pose"])
        else:
            side = 1.0 if self.np_random.random() < 0.5 else -1.0
            x = side * self.np_random.uniform(layout.START_X_MIN, layout.START_X_MAX)
            y = self.np_random.uniform(layout.START_Y_MIN, layout.START_Y_MAX)
            theta = self.np_random.uniform(-math.pi, math.pi)
        self._build_space(x, y, theta)
        assert self._space is not None and self._robot is not None
        overlaps = self._space.shape_query(next(iter(self._robot.shapes)))
        if overlaps:
            names = sorted({self._names.get(o.shape, "obstacle") for o in overlaps if o.shape is not None})
            self._space = None
            raise ValueError(f"start_pose ({x}, {y}, {theta}) overlaps {', '.join(names)}")
        self._steps = 0
        self.trajectory = [(x, y, theta)]
        return self._observe(), {"is_success": False, "collided": False, "collided_with": None}

    def step(self, action: np.ndarray) -> tuple[np.ndarray, float, bool, bool, dict[str, Any]]:
        if self._space is None or self._robot is None:
            raise RuntimeError("call reset() before step()")
        a = np.clip(np.asarray(action, dtype=np.float32).reshape(2), -1.0, 1.0)
        if not np.all(np.isfinite(a)):
            raise ValueError(f"action must be finite, got {action!r}")
        drive_l = 0.5 * WHEEL_FORCE_SCALE * float(a[0])
        drive_r = 0.5 * WHEEL_FORCE_SCALE * float(a[1])
        robot, space = self._robot, self._space
        dt = SAMPLE_TIME / PHYSICS_SUBSTEPS
        made_it = False
        for _ in range(PHYSICS_SUBSTEPS):
            theta = robot.angle
            c, s = math.cos(theta), math.sin(theta)
            vx, vy = robot.velocity
            v = vx * c + vy * s
            robot.velocity = (v * c, v * s)  # wheels do not slip sideways
            # Friction acts at the wheels: the linear part splits evenly, the angular part
            # is a force couple; together they give -LINEAR_FRICTION*v and -ANGULAR_FRICTION*w.
            linear = 0.5 * LINEAR_FRICTION * v
            couple = 0.5 * ANGULAR_FRICTION * robot.angular_velocity / WHEEL_HALF_TRACK
            robot.apply_force_at_local_point((drive_l - linear + couple, 0.0), (0.0, WHEEL_HALF_TRACK))
            robot.apply_force_at_local_point((drive_r - linear - couple, 0.0), (0.0, -WHEEL_HALF_TRACK))
            space.step(dt)
            if self._hit is not None:
                break
            if robot.position.y < layout.GOAL_Y:
                made_it = True
                break
        self._steps += 1
        collided = self._hit is not None
        made_it = made_it and not collided
        obs = self._observe()
        self.trajectory.append((robot.position.x, robot.position.y, robot.angle))
        r = reward(float(obs[0]), float(obs[1]), float(obs[5]), a, made_it, collided)
        terminated = made_it or collided
        truncated = not terminated and self._steps >= MAX_EPISODE_STEPS
        info = {"is_success": made_it, "collided": collided, "collided_with": self._hit}
        return obs, r, terminated, truncated, info

    def render(self) -> np.ndarray | None:
        if self.render_mode is None:
            gym.logger.warn("render() called without render_mode; use render_mode='rgb_array'")
            return None
        from embedrl.train.rendering import draw_frame

        return draw_frame(self.trajectory)

    def close(self) -> None:
        self._space = None
        self._robot = None
