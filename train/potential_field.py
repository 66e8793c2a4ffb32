"""The classical baseline: a potential-field controller, observation in, wheel forces out.

The reference study's "traditional controls approach": an attractive potential pulls the
robot towards a goal point below the gap, repulsive potentials push it away from every
shelf and wall, and the robot drives along the negative gradient. The gradient gives a
desired direction; a proportional heading loop turns the robot towards it (driving in
reverse when the direction is behind it, so it never turns more than 90 degrees) and the
forward force falls off with the heading error. Stateless: the action depends only on the
observation, like an exported policy.

The same controller drives every scenario; what it observes beyond the robot's own state adds terms:

- **moving shelf** (observations 6-8): the shelf repels from where it will be over the next
  ``sweep_time`` seconds (its rectangle stretched along its motion, and its wrapped-around copy), and
  across its path it pushes vertically, away from its middle line: a robot beside the shelf's path
  ducks under it or waits above it instead of being herded into a wall.
- **two robots** (observations 6-11): the other robot repels like an obstacle, and the robot farther
  from the gap yields: its goal becomes a waiting point at its own end of the aisle until the other
  robot is through (both robots compute the same order from what they observe).
"""

from __future__ import annotations

import math
from dataclasses import dataclass

import numpy as np

from embedrl.train import layout
from embedrl.train.robot import ROBOT_LENGTH, ROBOT_WIDTH
from embedrl.train.scenarios import (
    DEFAULT_SCENARIO,
    OTHER_ROBOT_FIELDS,
    SCENARIOS,
    SHELF_FIELDS,
    WAREHOUSE,
    field_indices,
)

_AISLE_END = layout.UPPER_SHELF_WIDTH / 2
"""|x| beyond which the robot is beside the shelves, not in the aisle between them [m]."""


@dataclass(frozen=True)
class PotentialFieldGains:
    """Tuning of :class:`PotentialFieldController` (SI units, map coordinates)."""

    goal_y: float = -0.7
    """The attractive goal lies at (0, goal_y) [m], below the gap, so the pull points down it."""
    aisle_y: float = 0.32
    """Beside the shelves the attractive sub-goal is the aisle mouth at this height [m]."""
    mouth_x: float = _AISLE_END + 0.15
    """|x| of the aisle mouth sub-goal [m]: clear of the shelf ends by the robot's size."""
    anisotropy: float = 0.4
    """Vertical scale of the conical goal potential in the aisle: below 1 the pull is mostly
    along the aisle far from the gap and turns down the gap only close to it."""
    repulsion: float = 0.0001
    """Gain of the repulsive potential ``0.5*k*(1/d - 1/d0)^2`` of each obstacle."""
    influence: float = 0.18
    """Range d0 [m] of the repulsive potential, measured from the robot's outline."""
    clearance: float = math.hypot(ROBOT_LENGTH, ROBOT_WIDTH) / 2
    """Distances are measured from a circle of this radius around the robot centre [m]."""
    min_distance: float = 0.02
    """Distances below this are treated as this [m], so the repulsion stays finite."""
    heading_gain: float = 1.5
    """Differential force per radian of heading error."""
    turn_damping: float = 0.1
    """Differential force per rad/s of turn rate (damps the heading loop)."""
    speed: float = 0.9
    """Common force when the robot faces the desired direction exactly."""
    lookahead: float = 0.35
    """The field is evaluated where the robot will be this many seconds ahead at its
    current speed, so it starts turning into the gap before it passes it [s]."""
    reverse_angle: float = math.radians(165)
    """Drive in reverse when the desired direction is further than this behind the heading."""
    sweep_time: float = 1.5
    """The moving shelf repels from everywhere it will be within this time [s]."""
    shelf_repulsion: float = 0.0004
    """Gain of the moving shelf's repulsive potential."""
    shelf_influence: float = 0.25
    """Range d0 [m] of the moving shelf's repulsive potential."""
    robot_repulsion: float = 0.0004
    """Gain of the other robot's repulsive potential."""
    robot_influence: float = 0.3
    """Range d0 [m] of the other robot's repulsive potential, from both robots' outlines."""
    wait_x: float = 0.75
    """|x| of the yielding robot's waiting point, on its own side of the gap, at the aisle height [m]."""
    priority_margin: float = 0.1
    """A robot yields when its way to the gap is longer than the other's by more than this [m]; when the
    two are within it, the robot on the right (x > 0) yields."""


class PotentialFieldController:
    """Maps an observation ``[x, y, sin, cos, v, w, ...]`` to wheel forces ``[F_L, F_R]`` in [-1, 1].

    ``scenario`` says what the observation holds beyond the first six values (see the module).
    """

    def __init__(self, gains: PotentialFieldGains | None = None, scenario: str = DEFAULT_SCENARIO) -> None:
        if scenario not in WAREHOUSE:
            raise ValueError(
                f"the potential-field controller drives the warehouse scenarios ({', '.join(WAREHOUSE)}), "
                f"not {scenario!r}"
            )
        self.gains = gains or PotentialFieldGains()
        self.scenario = scenario
        spec = SCENARIOS[scenario]  # which terms apply follows from what the scenario observes
        self._shelf = field_indices(spec, SHELF_FIELDS)
        self._other = field_indices(spec, OTHER_ROBOT_FIELDS)
        self._fixed = layout.FIXED_OBSTACLES if self._shelf else layout.OBSTACLES

    def attraction(self, x: float, y: float, wait: bool = False) -> tuple[float, float]:
        """Negative gradient of the attractive potential: a unit vector (or zero at the goal).

        Between the shelves (|x| < aisle end, y below the upper shelf) it is the cone
        ``sqrt(x^2 + (a*(y - goal_y))^2)``; beside them, the cone around the aisle mouth. A robot that
        ``wait``s is pulled to its waiting point instead once it is in the aisle.
        """
        g = self.gains
        in_aisle = abs(x) < g.mouth_x and y < layout.AISLE_WIDTH
        if in_aisle and wait:
            dx, dy = math.copysign(g.wait_x, x) - x, g.aisle_y - y
        elif in_aisle:
            a2 = g.anisotropy * g.anisotropy
            dx, dy = -x, -a2 * (y - g.goal_y)
        else:
            dx, dy = math.copysign(g.mouth_x, x) - x, g.aisle_y - y
        n = math.hypot(dx, dy)
        return (dx / n, dy / n) if n > 0.0 else (0.0, 0.0)

    def direction(
        self,
        x: float,
        y: float,
        shelf: tuple[float, float, float] | None = None,
        other: tuple[float, float] | None = None,
        wait: bool = False,
    ) -> tuple[float, float]:
        """Negative gradient of the total potential at (x, y); ``shelf`` is the moving shelf's
        ``(center_x, y0, vx)``, ``other`` the other robot's position, ``wait`` whether this robot yields."""
        g = self.gains
        fx, fy = self.attraction(x, y, wait)
        if shelf is not None:
            px, py = self._shelf_push(x, y, *shelf)
            fx, fy = fx + px, fy + py
        if other is not None:
            ox, oy = x - other[0], y - other[1]
            n = math.hypot(ox, oy)
            d = max(n - 2 * g.clearance, g.min_distance)
            if d < g.robot_influence and n > 0.0:
                push = g.robot_repulsion * (1.0 / d - 1.0 / g.robot_influence) / (d * d)
                fx, fy = fx + push * ox / n, fy + push * oy / n
        for rect in self._fixed:
            d, ux, uy = rect.distance(x, y)
            d = max(d - g.clearance, g.min_distance)
            if d < g.influence:
                push = g.repulsion * (1.0 / d - 1.0 / g.influence) / (d * d)
                fx += push * ux
                fy += push * uy
        return fx, fy

    def _shelf_push(self, x: float, y: float, center_x: float, y0: float, vx: float) -> tuple[float, float]:
        """Repulsion of the moving shelf over its next ``sweep_time`` seconds (and of its copy that
        will come in at the other side)."""
        g = self.gains
        half = layout.UPPER_SHELF_WIDTH / 2
        reach = vx * g.sweep_time
        middle = y0 + layout.UPPER_SHELF_DEPTH / 2
        fx = fy = 0.0
        for cx in (center_x, center_x - math.copysign(2 * layout.MOVING_SHELF_WRAP_X, center_x)):
            swept = layout.Rect(
                "swept shelf",
                cx - half + min(reach, 0.0),
                y0,
                cx + half + max(reach, 0.0),
                y0 + layout.UPPER_SHELF_DEPTH,
            )
            d, ux, uy = swept.distance(x, y)
            if swept.x0 - g.clearance <= x <= swept.x1 + g.clearance:  # across its path: duck or wait
                ux, uy = 0.0, (-1.0 if y < middle else 1.0)
                d = max(abs(y - middle) - layout.UPPER_SHELF_DEPTH / 2, 0.0)
            d = max(d - g.clearance, g.min_distance)
            if d < g.shelf_influence:
                push = g.shelf_repulsion * (1.0 / d - 1.0 / g.shelf_influence) / (d * d)
                fx += push * ux
                fy += push * uy
        return fx, fy

    def yields(self, x: float, y: float, other_x: float, other_y: float) -> bool:
        """Whether the robot at (x, y) lets the one at (other_x, other_y) through the gap first."""
        g = self.gains
        mine = abs(x) + abs(y - g.aisle_y)
        theirs = abs(other_x) + abs(other_y - g.aisle_y)
        if abs(mine - theirs) <= g.priority_margin:
            return x > 0.0
        return mine > theirs

    def __call__(self, obs: np.ndarray) -> np.ndarray:
        g = self.gains
        x, y, s, c, v, w = (float(o) for o in obs[:6])
        shelf = other = None
        wait = False
        if self._shelf is not None:
            dx, dy, vx = self._shelf
            shelf = (x + float(obs[dx]), y + float(obs[dy]), float(obs[vx]))
        elif self._other is not None and float(obs[self._other[2]]) > 0.5:
            other = (x + float(obs[self._other[0]]), y + float(obs[self._other[1]]))
            wait = self.yields(x, y, *other)
        fx, fy = self.direction(x + g.lookahead * v * c, y + g.lookahead * v * s, shelf, other, wait)
        error = math.atan2(fy, fx) - math.atan2(s, c)
        error = math.atan2(math.sin(error), math.cos(error))
        forward = 1.0
        if abs(error) > g.reverse_angle:  # the way on is behind: drive in reverse
            forward = -1.0
            error = math.atan2(math.sin(error + math.pi), math.cos(error + math.pi))
        common = forward * g.speed * max(math.cos(error), 0.0) ** 2
        turn = g.heading_gain * error - g.turn_damping * w
        return np.clip(np.array([common - turn, common + turn], dtype=np.float32), -1.0, 1.0)
