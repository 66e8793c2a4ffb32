"""The warehouse physics shared by every scenario: robots, fixed obstacles and a moving shelf in pymunk.

A :class:`World` is built from scratch at every reset (rebuilding, not restoring, keeps same-seed runs
bit-identical). One env step holds each robot's wheel forces for :data:`~train.robot.SAMPLE_TIME`, in
:data:`~train.robot.PHYSICS_SUBSTEPS` pymunk steps; the env calls :meth:`World.substep` once per
physics step and decides after each one whether its step ends early (a contact, the goal line).
"""

from __future__ import annotations

import math
from collections.abc import Sequence
from dataclasses import dataclass
from typing import Any

import numpy as np
import pymunk

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

DT = SAMPLE_TIME / PHYSICS_SUBSTEPS
"""One physics step [s]."""

_ROBOT = 1
_OBSTACLE = 2

Pose = tuple[float, float, float]


@dataclass(frozen=True)
class ShelfMotion:
    """The moving shelf: lower edge at ``y0``, centre starting at ``x``, constant speed ``vx``."""

    x: float
    y0: float
    vx: float


def checked_pose(pose: Any) -> Pose:
    """``(x, y, theta)`` as floats, inside the arena; ``ValueError`` otherwise."""
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


def robot_corners(x: float, y: float, theta: float) -> tuple[tuple[float, float], ...]:
    """The robot body's four corners at a pose: rear right, front right, front left, rear left."""
    c, s = math.cos(theta), math.sin(theta)
    hl, hw = ROBOT_LENGTH / 2, ROBOT_WIDTH / 2
    return tuple(
        (x + c * px - s * py, y + s * px + c * py) for px, py in ((-hl, -hw), (hl, -hw), (hl, hw), (-hl, hw))
    )


class World:
    """Robots (boxes on two wheels) among fixed obstacles and, optionally, the moving shelf.

    ``hits[i]`` names what robot ``i`` touched first (``None`` until it touches something); a robot
    touching another robot records ``"robot <j>"``. :meth:`remove` takes a robot out (it has left the
    arena); a removed robot neither moves nor collides.
    """

    def __init__(
        self,
        poses: Sequence[Pose],
        obstacles: Sequence[layout.Rect] = layout.OBSTACLES,
        shelf: ShelfMotion | None = None,
    ) -> None:
        space = pymunk.Space()
        self.robots: list[pymunk.Body] = []
        self._robot_of: dict[pymunk.Shape, int] = {}
        for i, (x, y, theta) in enumerate(poses):
            body = pymunk.Body(ROBOT_MASS, pymunk.moment_for_box(ROBOT_MASS, (ROBOT_LENGTH, ROBOT_WIDTH)))
            body.position = (x, y)
            body.angle = theta
            shape = pymunk.Poly.create_box(body, (ROBOT_LENGTH, ROBOT_WIDTH))
            shape.collision_type = _ROBOT
            space.add(body, shape)
            self.robots.append(body)
            self._robot_of[shape] = i
        self._names: dict[pymunk.Shape, str] = {}
        for rect in obstacles:
            shape = pymunk.Poly(space.static_body, list(rect.corners))
            shape.collision_type = _OBSTACLE
            space.add(shape)
            self._names[shape] = rect.name
        self.shelf: pymunk.Body | None = None
        self.shelf_y0 = 0.0
        if shelf is not None:
            body = pymunk.Body(body_type=pymunk.Body.KINEMATIC)
            body.position = (shelf.x, shelf.y0 + layout.UPPER_SHELF_DEPTH / 2)
            body.velocity = (shelf.vx, 0.0)
            box = pymunk.Poly.create_box(body, (layout.UPPER_SHELF_WIDTH, layout.UPPER_SHELF_DEPTH))
            box.collision_type = _OBSTACLE
            space.add(body, box)
            self._names[box] = "moving shelf"
            self.shelf, self.shelf_y0 = body, shelf.y0
        space.on_collision(_ROBOT, _OBSTACLE, begin=self._on_obstacle)
        space.on_collision(_ROBOT, _ROBOT, begin=self._on_robot)
        self.space = space
        self.hits: list[str | None] = [None] * len(self.robots)
        self.active = [True] * len(self.robots)

    # -- contacts ----------------------------------------------------------------------------------

    def _on_obstacle(self, arbiter: pymunk.Arbiter, space: pymunk.Space, data: Any) -> None:
        a, b = arbiter.shapes
        robot, other = (a, b) if a in self._robot_of else (b, a)
        i = self._robot_of[robot]
        if self.hits[i] is None:
            self.hits[i] = self._names.get(other, "obstacle")

    def _on_robot(self, arbiter: pymunk.Arbiter, space: pymunk.Space, data: Any) -> None:
        a, b = arbiter.shapes
        i, j = self._robot_of[a], self._robot_of[b]
        if self.hits[i] is None:
            self.hits[i] = f"robot {j}"
        if self.hits[j] is None:
            self.hits[j] = f"robot {i}"

    def overlaps(self, i: int) -> list[str]:
        """What robot ``i`` overlaps now (obstacles by name, other robots as ``robot <j>``)."""
        found = self.space.shape_query(next(iter(self.robots[i].shapes)))
        names = set()
        for hit in found:
            if hit.shape in self._names:
                names.add(self._names[hit.shape])
            elif hit.shape in self._robot_of and self.active[self._robot_of[hit.shape]]:
                names.add(f"robot {self._robot_of[hit.shape]}")
        return sorted(names)

    def remove(self, i: int) -> None:
        """Take robot ``i`` out of the world."""
        if self.active[i]:
            body = self.robots[i]
            self.space.remove(body, *body.shapes)
            self.active[i] = False

    # -- motion ------------------------------------------------------------------------------------

    def substep(self, actions: Sequence[np.ndarray | None]) -> None:
        """One physics step with each active robot's wheel forces ``[F_L, F_R]`` (``None``: no force)."""
        for body, action, active in zip(self.robots, actions, self.active, strict=True):
            if active:
                _drive(body, action)
        self.space.step(DT)
        if self.shelf is not None and abs(self.shelf.position.x) > layout.MOVING_SHELF_WRAP_X:
            x, y = self.shelf.position
            self.shelf.position = (x - math.copysign(2 * layout.MOVING_SHELF_WRAP_X, x), y)
            self.space.reindex_shapes_for_body(self.shelf)

    def pose(self, i: int) -> Pose:
        body = self.robots[i]
        return body.position.x, body.position.y, body.angle

    def robot_state(self, i: int) -> tuple[float, float, float, float, float, float]:
        """``(x, y, sin theta, cos theta, v, w)`` of robot ``i``: ``v`` is the speed along the heading."""
        r = self.robots[i]
        c, s = math.cos(r.angle), math.sin(r.angle)
        v = r.velocity.x * c + r.velocity.y * s
        return r.position.x, r.position.y, s, c, v, r.angular_velocity

    def shelf_rect(self) -> layout.Rect | None:
        """The moving shelf where it is now."""
        if self.shelf is None:
            return None
        return layout.moving_shelf(self.shelf.position.x, self.shelf_y0)


def _drive(robot: pymunk.Body, action: np.ndarray | None) -> None:
    """Apply one physics step's wheel forces and friction; the wheels do not slip sideways."""
    drive_l = 0.0 if action is None else 0.5 * WHEEL_FORCE_SCALE * float(action[0])
    drive_r = 0.0 if action is None else 0.5 * WHEEL_FORCE_SCALE * float(action[1])
    theta = robot.angle
    c, s = math.cos(theta), math.sin(theta)
    vx, vy = robot.velocity
    v = vx * c + vy * s
    robot.velocity = (v * c, v * s)
    # Friction acts at the wheels: the linear part splits evenly, the angular part is a force couple;
    # together they give -LINEAR_FRICTION*v and -ANGULAR_FRICTION*w.
    linear = 0.5 * LINEAR_FRICTION * v
    couple = 0.5 * ANGULAR_FRICTION * robot.angular_velocity / WHEEL_HALF_TRACK
    robot.apply_force_at_local_point((drive_l - linear + couple, 0.0), (0.0, WHEEL_HALF_TRACK))
    robot.apply_force_at_local_point((drive_r - linear - couple, 0.0), (0.0, -WHEEL_HALF_TRACK))
