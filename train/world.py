"""The warehouse physics shared by every scenario: robots, fixed obstacles and a moving shelf in pymunk.

An env keeps one :class:`World` and :meth:`World.reset` s it for each episode: the fixed obstacles stay,
new robots (and a new moving shelf) replace the old ones, whose contacts leave with them. One env step
holds each robot's wheel forces for :data:`~train.robot.SAMPLE_TIME`, in
:data:`~train.robot.PHYSICS_SUBSTEPS` pymunk steps, ending early at a contact or at the goal line
(:meth:`World.drive_one` for one robot, :meth:`World.substep` per physics step for several).

The per-step work talks to chipmunk through pymunk's low-level API (``pymunk._chipmunk.lib``, the C
functions pymunk's properties call) on plain floats: the same arithmetic in the same order as through
pymunk's objects. Reset and step together are three times as fast as rebuilding the world and stepping
through pymunk's objects, and every recorded episode of every scenario replays bit for bit
(``tests/test_env_recordings.py``: recorded before either change).
"""

from __future__ import annotations

import math
from collections.abc import Sequence
from dataclasses import dataclass
from typing import Any

import numpy as np
import pymunk
from pymunk._chipmunk import lib as _cp

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
_DRIVE = 0.5 * WHEEL_FORCE_SCALE
"""Each wheel's force per unit of action [N]."""
_HALF_LINEAR = 0.5 * LINEAR_FRICTION
_HALF_ANGULAR = 0.5 * ANGULAR_FRICTION
_LEFT_WHEEL = (0.0, WHEEL_HALF_TRACK)
_RIGHT_WHEEL = (0.0, -WHEEL_HALF_TRACK)
_NO_DRIVE = (0.0, 0.0)

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
        self.space = space
        self._space_ptr = space._space
        self._names: dict[pymunk.Shape, str] = {}
        for rect in obstacles:
            shape = pymunk.Poly(space.static_body, list(rect.corners))
            shape.collision_type = _OBSTACLE
            space.add(shape)
            self._names[shape] = rect.name
        space.on_collision(_ROBOT, _OBSTACLE, begin=self._on_obstacle)
        space.on_collision(_ROBOT, _ROBOT, begin=self._on_robot)
        self.robots: list[pymunk.Body] = []
        self.shelf: pymunk.Body | None = None
        self.reset(poses, shelf)

    def reset(self, poses: Sequence[Pose], shelf: ShelfMotion | None = None) -> None:
        """Start again with new robots at ``poses`` (and a new moving shelf): the old ones and every contact
        they had leave the space; the fixed obstacles stay."""
        space = self.space
        for body in [*self.robots, *([self.shelf] if self.shelf is not None else [])]:
            if body.space is not None:  # not already taken out by remove()
                space.remove(body, *body.shapes)
        self._names = {shape: name for shape, name in self._names.items() if shape.body is space.static_body}
        self.robots = []
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
        self.shelf = None
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
        self._body_ptrs = [body._body for body in self.robots]
        self._shelf_ptr = self.shelf._body if self.shelf is not None else None
        self._drives: list[tuple[float, float]] = [_NO_DRIVE] * len(self.robots)
        self._pending = True
        """Whether pymunk has work for its next step (bodies to check, removed shapes to forget)."""
        self.hits: list[str | None] = [None] * len(self.robots)
        self.active = [True] * len(self.robots)

    _POINTERS = ("_space_ptr", "_body_ptrs", "_shelf_ptr")
    """Chipmunk's pointers, which a pickle (a training checkpoint) leaves out and a load finds again."""

    def __getstate__(self) -> dict[str, Any]:
        return {k: v for k, v in self.__dict__.items() if k not in self._POINTERS}

    def __setstate__(self, state: dict[str, Any]) -> None:
        self.__dict__.update(state)
        self._space_ptr = self.space._space
        self._body_ptrs = [body._body for body in self.robots]
        self._shelf_ptr = self.shelf._body if self.shelf is not None else None
        self._pending = True

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
            self._pending = True

    # -- motion ------------------------------------------------------------------------------------

    def hold(self, actions: Sequence[np.ndarray | None]) -> None:
        """Each robot's wheel forces ``[F_L, F_R]`` (``None``: no force) for the substeps that follow."""
        self._drives = [
            _NO_DRIVE if a is None else (_DRIVE * float(a[0]), _DRIVE * float(a[1])) for a in actions
        ]

    def substep(self, actions: Sequence[np.ndarray | None] | None = None) -> None:
        """One physics step with the wheel forces :meth:`hold` set (or ``actions``, held from now on)."""
        if actions is not None:
            self.hold(actions)
        for ptr, drive, active in zip(self._body_ptrs, self._drives, self.active, strict=True):
            if active:
                _drive(ptr, drive)
        if self._pending:  # bodies added or removed: pymunk's own step checks and clears its records
            self.space.step(DT)
            self._pending = False
        else:  # nothing pending, and the contact callbacks never add or remove: chipmunk's step is all
            _cp.cpSpaceStep(self._space_ptr, DT)
        if self._shelf_ptr is not None:
            self._wrap_shelf()

    def _wrap_shelf(self) -> None:
        """The moving shelf past the aisle's end comes back at the other end."""
        x = _cp.cpBodyGetPosition(self._shelf_ptr).x
        if abs(x) > layout.MOVING_SHELF_WRAP_X:
            assert self.shelf is not None
            y = self.shelf.position.y
            self.shelf.position = (x - math.copysign(2 * layout.MOVING_SHELF_WRAP_X, x), y)
            self.space.reindex_shapes_for_body(self.shelf)

    def drive_one(self, goal_y: float) -> bool:
        """Robot 0 of a one-robot world through one env step: up to :data:`PHYSICS_SUBSTEPS` physics steps
        with its held forces, ending early at a contact or once it is below ``goal_y``. Whether it got
        below ``goal_y`` without a contact. The same arithmetic as :meth:`substep` and :func:`_drive`,
        with every name local: this loop is most of an env step's time."""
        body, space = self._body_ptrs[0], self._space_ptr
        drive_l, drive_r = self._drives[0]
        get_angle, get_velocity = _cp.cpBodyGetAngle, _cp.cpBodyGetVelocity
        set_velocity = _cp.cpBodySetVelocity
        get_w, get_position = _cp.cpBodyGetAngularVelocity, _cp.cpBodyGetPosition
        push, step = _cp.cpBodyApplyForceAtLocalPoint, _cp.cpSpaceStep
        cos, sin, hits = math.cos, math.sin, self.hits
        half_linear, half_angular, half_track = _HALF_LINEAR, _HALF_ANGULAR, WHEEL_HALF_TRACK
        left, right, dt = _LEFT_WHEEL, _RIGHT_WHEEL, DT
        pending, shelf = self._pending, self._shelf_ptr is not None
        for _ in range(PHYSICS_SUBSTEPS):
            theta = get_angle(body)
            c, s = cos(theta), sin(theta)
            velocity = get_velocity(body)
            v = velocity.x * c + velocity.y * s
            set_velocity(body, (v * c, v * s))
            linear = half_linear * v
            couple = half_angular * get_w(body) / half_track
            push(body, (drive_l - linear + couple, 0.0), left)
            push(body, (drive_r - linear - couple, 0.0), right)
            if pending:
                self.space.step(dt)
                pending = self._pending = False
            else:
                step(space, dt)
            if shelf:
                self._wrap_shelf()
            if hits[0] is not None:
                return False
            if get_position(body).y < goal_y:
                return True
        return False

    def y(self, i: int) -> float:
        """Robot ``i``'s y [m]."""
        return float(_cp.cpBodyGetPosition(self._body_ptrs[i]).y)

    def pose(self, i: int) -> Pose:
        body = self._body_ptrs[i]
        position = _cp.cpBodyGetPosition(body)
        return position.x, position.y, _cp.cpBodyGetAngle(body)

    def robot_state(self, i: int) -> tuple[float, float, float, float, float, float]:
        """``(x, y, sin theta, cos theta, v, w)`` of robot ``i``: ``v`` is the speed along the heading."""
        body = self._body_ptrs[i]
        theta = _cp.cpBodyGetAngle(body)
        c, s = math.cos(theta), math.sin(theta)
        velocity = _cp.cpBodyGetVelocity(body)
        v = velocity.x * c + velocity.y * s
        position = _cp.cpBodyGetPosition(body)
        return position.x, position.y, s, c, v, _cp.cpBodyGetAngularVelocity(body)

    def shelf_state(self) -> tuple[float, float]:
        """The moving shelf's centre x [m] and speed along the aisle [m/s]."""
        assert self._shelf_ptr is not None
        return _cp.cpBodyGetPosition(self._shelf_ptr).x, _cp.cpBodyGetVelocity(self._shelf_ptr).x

    def shelf_rect(self) -> layout.Rect | None:
        """The moving shelf where it is now."""
        if self.shelf is None:
            return None
        return layout.moving_shelf(self.shelf.position.x, self.shelf_y0)


class ObsBounds:
    """An observation's float32 bounds: :meth:`clip` gives what ``np.clip`` gives on the state as float32,
    in a fraction of its time (an env step's observation is 6 to 12 values)."""

    def __init__(self, low: np.ndarray, high: np.ndarray) -> None:
        self.pairs = list(zip(low.astype(np.float32).tolist(), high.astype(np.float32).tolist(), strict=True))

    def clip(self, state: Sequence[float]) -> np.ndarray:
        """``state`` clipped, as float32. The same bits as clipping after the rounding: the bounds are
        float32, so a value inside them rounds inside them, and one outside becomes the bound either way;
        a NaN stays NaN."""
        return np.array(
            [hi if v > hi else lo if v < lo else v for v, (lo, hi) in zip(state, self.pairs, strict=True)],
            dtype=np.float32,
        )


def held_action(action: Any, who: str = "action") -> np.ndarray:
    """A robot's action as the env applies it: float32, clipped to [-1, 1] (an infinite value to its
    bound); ``ValueError`` for a NaN or a wrong shape."""
    a = np.array(action, dtype=np.float32).reshape(2)
    left, right = a.tolist()
    if -1.0 <= left <= 1.0 and -1.0 <= right <= 1.0:  # already inside: np.clip would change nothing
        return a
    np.minimum(np.maximum(a, -1.0, out=a), 1.0, out=a)
    if a[0] != a[0] or a[1] != a[1]:
        raise ValueError(f"{who} must be finite, got {action!r}")
    return a


def _drive(body: Any, drive: tuple[float, float]) -> None:
    """Apply one physics step's wheel forces and friction to a chipmunk body; the wheels do not slip
    sideways."""
    drive_l, drive_r = drive
    theta = _cp.cpBodyGetAngle(body)
    c, s = math.cos(theta), math.sin(theta)
    velocity = _cp.cpBodyGetVelocity(body)
    v = velocity.x * c + velocity.y * s
    _cp.cpBodySetVelocity(body, (v * c, v * s))
    # Friction acts at the wheels: the linear part splits evenly, the angular part is a force couple;
    # together they give -LINEAR_FRICTION*v and -ANGULAR_FRICTION*w.
    linear = _HALF_LINEAR * v
    couple = _HALF_ANGULAR * _cp.cpBodyGetAngularVelocity(body) / WHEEL_HALF_TRACK
    _cp.cpBodyApplyForceAtLocalPoint(body, (drive_l - linear + couple, 0.0), _LEFT_WHEEL)
    _cp.cpBodyApplyForceAtLocalPoint(body, (drive_r - linear - couple, 0.0), _RIGHT_WHEEL)
