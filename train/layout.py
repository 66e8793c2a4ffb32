"""The warehouse map: shelves, walls, start regions and the goal line, in metres.

Shelf-aligned coordinates: x to the right along the shelves, y up, origin in the
middle of the gap between the two lower shelves, at their upper edge. The lower
shelves stand on the bottom wall, so the gap is the only way down: the robot has
made it when its centre passes below ``GOAL_Y``, the lower edge of the shelves.

Why the lower shelves are shallow: with the study's reward term
``0.06*exp(-3y)`` the reward per step turns positive below y ~ -0.14 (with the
robot centred in the gap). A goal line at ``-LOWER_SHELF_DEPTH = -0.15`` keeps
every non-terminal step at most +0.004, so waiting in the gap never pays more
than driving through it.

Everything here is a plain constant or a frozen value object: the environment,
the potential-field controller and the renderers read the same map.
"""

from __future__ import annotations

import math
from dataclasses import dataclass

GAP_WIDTH = 0.6
"""Clear width between the two lower shelves [m] (the robot is 0.2 m wide)."""
LOWER_SHELF_WIDTH = 0.8
"""Length of each lower shelf along x [m]."""
LOWER_SHELF_DEPTH = 0.15
"""Depth of the lower shelves along y [m]; their lower edge is the goal line."""
AISLE_WIDTH = 0.6
"""Clear distance between the lower shelves and the upper shelf [m]."""
UPPER_SHELF_WIDTH = 2.2
"""Length of the upper shelf along x [m]; it spans the whole lower row."""
UPPER_SHELF_DEPTH = 0.3
"""Depth of the upper shelf along y [m]."""
ARENA_HALF_WIDTH = 1.8
"""Side walls at x = -1.8 m and x = +1.8 m."""
ARENA_TOP = 1.3
"""Top wall at y = 1.3 m."""
GOAL_Y = -LOWER_SHELF_DEPTH
"""Success: the robot centre is below this line (only reachable through the gap)."""
ARENA_BOTTOM = GOAL_Y
"""The bottom wall runs along the lower shelves' lower edge, open at the gap."""

START_X_MIN = 1.35
"""Start positions have |x| in [START_X_MIN, START_X_MAX] [m]: beside the shelves."""
START_X_MAX = 1.6
START_Y_MIN = 0.1
"""Start positions have y in [START_Y_MIN, START_Y_MAX] [m]."""
START_Y_MAX = 1.0

WALL_THICKNESS = 0.1
"""Walls are boxes of this thickness just outside the arena [m]."""


@dataclass(frozen=True)
class Rect:
    """An axis-aligned rectangle ``[x0, x1] x [y0, y1]`` with a name for reports."""

    name: str
    x0: float
    y0: float
    x1: float
    y1: float

    @property
    def corners(self) -> tuple[tuple[float, float], ...]:
        """Counter-clockwise corners, starting at the lower left."""
        return ((self.x0, self.y0), (self.x1, self.y0), (self.x1, self.y1), (self.x0, self.y1))

    @property
    def center(self) -> tuple[float, float]:
        return ((self.x0 + self.x1) / 2, (self.y0 + self.y1) / 2)

    def distance(self, x: float, y: float) -> tuple[float, float, float]:
        """Distance from (x, y) to the rectangle and the unit vector pointing away from it.

        Returns ``(d, ux, uy)``; inside the rectangle d is 0 and the vector points
        out through the nearest side.
        """
        cx = min(max(x, self.x0), self.x1)
        cy = min(max(y, self.y0), self.y1)
        dx, dy = x - cx, y - cy
        d = math.hypot(dx, dy)
        if d > 0.0:
            return d, dx / d, dy / d
        # Inside: leave through the nearest side.
        exits = (
            (x - self.x0, -1.0, 0.0),
            (self.x1 - x, 1.0, 0.0),
            (y - self.y0, 0.0, -1.0),
            (self.y1 - y, 0.0, 1.0),
        )
        _, ux, uy = min(exits)
        return 0.0, ux, uy


_HALF_GAP = GAP_WIDTH / 2
_LOWER_OUTER = _HALF_GAP + LOWER_SHELF_WIDTH
_UPPER_Y0 = AISLE_WIDTH
_T = WALL_THICKNESS
_H = ARENA_HALF_WIDTH

SHELVES: tuple[Rect, ...] = (
    Rect("left shelf", -_LOWER_OUTER, GOAL_Y, -_HALF_GAP, 0.0),
    Rect("right shelf", _HALF_GAP, GOAL_Y, _LOWER_OUTER, 0.0),
    Rect(
        "upper shelf", -UPPER_SHELF_WIDTH / 2, _UPPER_Y0, UPPER_SHELF_WIDTH / 2, _UPPER_Y0 + UPPER_SHELF_DEPTH
    ),
)
"""The three shelves: two lower ones with the gap between them, one upper one."""

WALLS: tuple[Rect, ...] = (
    Rect("left wall", -_H - _T, ARENA_BOTTOM - _T, -_H, ARENA_TOP + _T),
    Rect("right wall", _H, ARENA_BOTTOM - _T, _H + _T, ARENA_TOP + _T),
    Rect("top wall", -_H - _T, ARENA_TOP, _H + _T, ARENA_TOP + _T),
    Rect("bottom left wall", -_H - _T, ARENA_BOTTOM - _T, -_HALF_GAP, ARENA_BOTTOM),
    Rect("bottom right wall", _HALF_GAP, ARENA_BOTTOM - _T, _H + _T, ARENA_BOTTOM),
)
"""Arena walls; the bottom wall is open under the gap."""

OBSTACLES: tuple[Rect, ...] = SHELVES + WALLS
"""Everything the robot must not touch."""

VIEW = Rect("view", -_H - _T, GOAL_Y - 0.35, _H + _T, ARENA_TOP + _T)
"""The area drawn by the renderers, including the exit below the gap."""

# -- The moving-shelf scenario: the upper shelf moves along the aisle and wraps around. ---------------

MOVING_SHELF_Y_MIN = 0.5
"""The moving shelf's lower edge is drawn uniformly from [MOVING_SHELF_Y_MIN, MOVING_SHELF_Y_MAX] [m]:
the aisle under it is never narrower than 0.5 m (the robot turns in 0.32 m)."""
MOVING_SHELF_Y_MAX = 0.8
MOVING_SHELF_SPEED_MIN = 0.2
"""The moving shelf's speed is drawn uniformly from [MOVING_SHELF_SPEED_MIN, MOVING_SHELF_SPEED_MAX] [m/s],
towards a random side: up to two thirds of the robot's top speed."""
MOVING_SHELF_SPEED_MAX = 0.45
MOVING_SHELF_WRAP_X = ARENA_HALF_WIDTH + UPPER_SHELF_WIDTH / 2
"""When the moving shelf's centre passes |x| = this, it has left the arena through the side wall; it
reappears at the same height on the opposite side, entering the arena again."""
MOVING_SHELF_START_CLEARANCE = 0.25
"""At the start the moving shelf is at least this far from the robot's centre [m]..."""
MOVING_SHELF_START_LEAD = 2.5
"""... and, when the robot stands in the shelf's path, at least this many seconds away from reaching it
(wrap-around included): every start leaves time to get out of the way [s]."""
FIXED_OBSTACLES: tuple[Rect, ...] = SHELVES[:2] + WALLS
"""What stays put in the moving-shelf scenario: the lower shelves and the walls."""


def moving_shelf(center_x: float, y0: float) -> Rect:
    """The moving shelf with its centre at ``center_x`` and its lower edge at ``y0``."""
    half = UPPER_SHELF_WIDTH / 2
    return Rect("moving shelf", center_x - half, y0, center_x + half, y0 + UPPER_SHELF_DEPTH)
