"""The classical baseline: a potential-field controller, observation in, wheel forces out.

The reference study's "traditional controls approach": an attractive potential pulls the
robot towards a goal point below the gap, repulsive potentials push it away from every
shelf and wall, and the robot drives along the negative gradient. The gradient gives a
desired direction; a proportional heading loop turns the robot towards it (driving in
reverse when the direction is behind it, so it never turns more than 90 degrees) and the
forward force falls off with the heading error. Stateless: the action depends only on the
observation, like an exported policy.
"""

from __future__ import annotations

import math
from dataclasses import dataclass

import numpy as np

from embedrl.train import layout
from embedrl.train.robot import ROBOT_LENGTH, ROBOT_WIDTH

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


class PotentialFieldController:
    """Maps an observation ``[x, y, sin, cos, v, w]`` to wheel forces ``[F_L, F_R]`` in [-1, 1]."""

    def __init__(self, gains: PotentialFieldGains | None = None) -> None:
        self.gains = gains or PotentialFieldGains()

    def attraction(self, x: float, y: float) -> tuple[float, float]:
        """Negative gradient of the attractive potential: a unit vector (or zero at the goal).

        Between the shelves (|x| < aisle end, y below the upper shelf) it is the cone
        ``sqrt(x^2 + (a*(y - goal_y))^2)``; beside them, the cone around the aisle mouth.
        """
        g = self.gains
        in_aisle = abs(x) < g.mouth_x and y < layout.AISLE_WIDTH
        if in_aisle:
            a2 = g.anisotropy * g.anisotropy
            dx, dy = -x, -a2 * (y - g.goal_y)
        else:
            dx, dy = math.copysign(g.mouth_x, x) - x, g.aisle_y - y
        n = math.hypot(dx, dy)
        return (dx / n, dy / n) if n > 0.0 else (0.0, 0.0)

    def direction(self, x: float, y: float) -> tuple[float, float]:
        """Negative gradient of the total potential at (x, y)."""
        g = self.gains
        fx, fy = self.attraction(x, y)
        for rect in layout.OBSTACLES:
            d, ux, uy = rect.distance(x, y)
            d = max(d - g.clearance, g.min_distance)
            if d < g.influence:
                push = g.repulsion * (1.0 / d - 1.0 / g.influence) / (d * d)
                fx += push * ux
                fy += push * uy
        return fx, fy

    def __call__(self, obs: np.ndarray) -> np.ndarray:
        g = self.gains
        x, y, s, c, v, w = (float(o) for o in obs[:6])
        fx, fy = self.direction(x + g.lookahead * v * c, y + g.lookahead * v * s)
        error = math.atan2(fy, fx) - math.atan2(s, c)
        error = math.atan2(math.sin(error), math.cos(error))
        forward = 1.0
        if abs(error) > g.reverse_angle:  # the way on is behind: drive in reverse
            forward = -1.0
            error = math.atan2(math.sin(error + math.pi), math.cos(error + math.pi))
        common = forward * g.speed * max(math.cos(error), 0.0) ** 2
        turn = g.heading_gain * error - g.turn_damping * w
        return np.clip(np.array([common - turn, common + turn], dtype=np.float32), -1.0, 1.0)
