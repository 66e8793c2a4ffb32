"""``embedrl/WarehouseMovingShelf-v0``: the warehouse robot while the upper shelf moves along the aisle."""

from __future__ import annotations

import math
from typing import Any

import numpy as np

from embedrl.train import layout
from embedrl.train.robot import ROBOT_LENGTH, ROBOT_WIDTH
from embedrl.train.scenarios import MOVING_SHELF, MOVING_SHELF_PARTIAL
from embedrl.train.warehouse_env import WarehouseRobotEnv
from embedrl.train.world import Pose, ShelfMotion, World

ROBOT_REACH = math.hypot(ROBOT_LENGTH, ROBOT_WIDTH) / 2
"""The robot's outline lies within this distance of its centre [m]."""
MAX_SHELF_DRAWS = 1000
"""Draws of the shelf's start position before giving up on a start pose (never reached from the
documented start region: the shelf covers at most 2.5 m of its 5.8 m track at the robot's height)."""


class WarehouseMovingShelfEnv(WarehouseRobotEnv):
    """The static warehouse task while the upper shelf moves along the aisle and wraps around.

    ## Description
    The map, robot, physics, sample time and goal of ``embedrl/WarehouseRobot-v0``, except that the upper
    shelf (2.2 m x 0.3 m) moves: at reset its lower edge is placed at a random height in [0.5, 0.8] m and
    it moves along x at a constant random speed in [0.2, 0.45] m/s towards a random side. When it has left
    the arena through a side wall (its centre at |x| > 2.9 m) it reappears at the opposite side at the
    same height and keeps going. It pushes nothing aside: touching it is a collision like any other.

    Unlike the reference study's agent, which could not see the obstacle (and counted "false successes"
    when the shelf approached unseen), this robot **observes the shelf**: its position relative to the
    robot and its velocity (observations 6-8). A deliberate improvement: a deployed robot has sensors.

    ## Action Space
    ``Box(-1, 1, (2,), float32)``, held for one sample time (0.3 s):

    | Num | Action                    | Min | Max |
    |-----|---------------------------|-----|-----|
    | 0   | left wheel force ``F_L``  | -1  | 1   |
    | 1   | right wheel force ``F_R`` | -1  | 1   |

    ## Observation Space
    ``Box(float32, (9,))``, shelf-aligned coordinates as in the static env:

    | Num | Observation                            | Min   | Max  | Unit  |
    |-----|----------------------------------------|-------|------|-------|
    | 0   | x, position along the shelves          | -1.8  | 1.8  | m     |
    | 1   | y, position across the shelves         | -0.15 | 1.3  | m     |
    | 2   | sin(theta), heading (0 = along +x)     | -1    | 1    |       |
    | 3   | cos(theta)                             | -1    | 1    |       |
    | 4   | v, forward speed                       | -0.7  | 0.7  | m/s   |
    | 5   | w, turn rate (counter-clockwise)       | -2.0  | 2.0  | rad/s |
    | 6   | moving shelf centre x minus robot x    | -4.7  | 4.7  | m     |
    | 7   | moving shelf lower edge y minus robot y | -0.8  | 0.95 | m     |
    | 8   | moving shelf velocity along x          | -0.45 | 0.45 | m/s   |

    ## Rewards
    As the static env: ``reward="thesis"`` (default) is the study's eq. 19, ``reward="potential-field"``
    the study's changing-environment reward, whose contours follow the moving shelf where it is at the end
    of the step, averaged over the robot's four corners (:mod:`train.rewards`).

    ## Starting State
    The robot as in the static env. The shelf's height, speed and direction are drawn first, then its
    centre uniformly in [-2.9, 2.9] m, redrawn until the start is fair: the shelf at least 0.25 m from the
    robot's centre and, if the robot stands in its path, at least 2.5 s from reaching it (around the
    wrap-around included).
    ``reset(options={"start_pose": (x, y, theta), "shelf": (center_x, y0, vx)})`` fixes either.

    ## Episode End
    - Terminated, success: the robot centre passes below y = -0.15 m (through the gap) without a contact.
    - Terminated, collision: the robot touches a shelf (the moving one included) or a wall.
    - Truncated: 200 steps (60 s).

    ``info`` always carries ``is_success``, ``collided`` and ``collided_with`` (or ``None``).

    ## Arguments
    ``gymnasium.make("embedrl/WarehouseMovingShelf-v0", render_mode="rgb_array", reward="thesis")``

    ## Version History
    - v0: initial version.
    """

    SPEC = MOVING_SHELF
    _RESET_OPTIONS = ("start_pose", "shelf")

    def _make_world(self, pose: Pose, options: dict[str, Any]) -> World:
        if options.get("shelf") is not None:
            motion = _checked_shelf(options["shelf"])
        else:
            motion = self._draw_shelf(pose)
        if self._world is None:
            return World([pose], layout.FIXED_OBSTACLES, motion)
        self._world.reset([pose], motion)
        return self._world

    def _draw_shelf(self, pose: Pose) -> ShelfMotion:
        rng = self.np_random
        y0 = rng.uniform(layout.MOVING_SHELF_Y_MIN, layout.MOVING_SHELF_Y_MAX)
        speed = rng.uniform(layout.MOVING_SHELF_SPEED_MIN, layout.MOVING_SHELF_SPEED_MAX)
        vx = speed if rng.random() < 0.5 else -speed
        for _ in range(MAX_SHELF_DRAWS):
            x = rng.uniform(-layout.MOVING_SHELF_WRAP_X, layout.MOVING_SHELF_WRAP_X)
            if _fair_start(x, y0, vx, pose):
                return ShelfMotion(x, y0, vx)
        raise ValueError(f"no room for the moving shelf at height {y0:.3f} m around the start pose {pose}")

    def _obstacles(self) -> tuple[layout.Rect, ...]:
        return layout.FIXED_OBSTACLES + self._moving_obstacles()

    def _moving_obstacles(self) -> tuple[layout.Rect, ...]:
        assert self._world is not None
        shelf = self._world.shelf_rect()
        return () if shelf is None else (shelf,)

    def full_observation(self) -> np.ndarray:
        """Everything the robot could observe: the observation of ``embedrl/WarehouseMovingShelf-v0``."""
        world = self._world
        assert world is not None and world.shelf is not None
        x, y, *rest = world.robot_state(0)
        shelf_x, shelf_vx = world.shelf_state()
        return np.array((x, y, *rest, shelf_x - x, world.shelf_y0 - y, shelf_vx), dtype=np.float64)

    def _observe(self) -> np.ndarray:
        # The spec's fields, by name, from the full observation.
        full = dict(zip((f.name for f in MOVING_SHELF.observation), self.full_observation(), strict=True))
        return self._bounds.clip(tuple(full[f.name] for f in self.SPEC.observation))


class WarehouseMovingShelfPartialEnv(WarehouseMovingShelfEnv):
    """``embedrl/WarehouseMovingShelfPartial-v0``: the moving shelf, observed without its velocity.

    Everything as ``embedrl/WarehouseMovingShelf-v0`` except the observation, which has the shelf's position
    relative to the robot but not its velocity: from one observation a policy cannot tell which way the
    shelf moves (a policy with memory can, from two).

    ## Observation Space
    ``Box(float32, (8,))``: observations 0-7 of ``embedrl/WarehouseMovingShelf-v0`` (its table), the shelf's
    position relative to the robot included; its observation 8, the shelf's velocity, left out.

    ## Version History
    - v0: initial version.
    """

    SPEC = MOVING_SHELF_PARTIAL


def _fair_start(x: float, y0: float, vx: float, pose: Pose) -> bool:
    """Whether a shelf at ``x`` leaves the robot at ``pose`` room and time (see :mod:`train.layout`)."""
    rx, ry = pose[0], pose[1]
    if layout.moving_shelf(x, y0).distance(rx, ry)[0] < layout.MOVING_SHELF_START_CLEARANCE:
        return False
    in_path = y0 - ROBOT_REACH < ry < y0 + layout.UPPER_SHELF_DEPTH + ROBOT_REACH
    if not in_path:
        return True
    # Distance the shelf's leading edge travels before it reaches the robot's outline, around the track.
    leading = x + math.copysign(layout.UPPER_SHELF_WIDTH / 2, vx)
    track = 2 * layout.MOVING_SHELF_WRAP_X
    ahead = ((rx - leading) * math.copysign(1.0, vx)) % track - ROBOT_REACH
    return ahead >= abs(vx) * layout.MOVING_SHELF_START_LEAD


def _checked_shelf(value: Any) -> ShelfMotion:
    try:
        x, y0, vx = (float(v) for v in value)
    except (TypeError, ValueError):
        raise ValueError(f"shelf must be three numbers (center_x, y0, vx), got {value!r}") from None
    if not (
        abs(x) <= layout.MOVING_SHELF_WRAP_X
        and layout.MOVING_SHELF_Y_MIN <= y0 <= layout.MOVING_SHELF_Y_MAX
        and abs(vx) <= layout.MOVING_SHELF_SPEED_MAX
        and all(math.isfinite(v) for v in (x, y0, vx))
    ):
        raise ValueError(
            f"shelf ({x}, {y0}, {vx}) is outside |center_x| <= {layout.MOVING_SHELF_WRAP_X}, "
            f"{layout.MOVING_SHELF_Y_MIN} <= y0 <= {layout.MOVING_SHELF_Y_MAX}, "
            f"|vx| <= {layout.MOVING_SHELF_SPEED_MAX}"
        )
    return ShelfMotion(x, y0, vx)
