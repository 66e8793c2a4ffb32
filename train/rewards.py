"""The warehouse rewards: the reference study's eq. 19 (``thesis``) and its potential-field variant.

``thesis``, on the state after the step::

    r = 0.06 exp(-3y) + 0.05 exp(-8x^2) - 0.14 - 0.001 w^2 - 0.01 (F_L^2 + F_R^2)
        + bonus * made_it - 2 * collided

``potential-field`` (the study's changing and multi-agent scenarios) replaces the position terms by the
mean, over the robot body's four corners, of a field that adds repulsive "contours" around every
obstacle (the moving shelf where it is now, the other robot where it is now)::

    field(p) = 0.06 exp(-3 p_y) + 0.05 exp(-8 p_x^2) - 0.05 * sum_o exp(-d_o(p) / 0.05 m)
    r = mean_{corners c} field(c) - 0.14 - 0.001 w^2 - 0.01 (F_L^2 + F_R^2) + bonus * made_it - 2 * collided

``d_o(p)`` is the distance from the point to obstacle ``o`` (0 inside it): a corner touching an obstacle
feels -0.05, one 0.15 m away -0.0025. Averaging over the corners lets a corner about to touch something
be felt even when the centre is clear.

``shaped`` is ``thesis`` plus potential-based shaping (Ng, Harada and Russell 1999), which provably leaves
the optimal policy unchanged::

    r' = r + gamma * Phi(s') - Phi(s),   Phi(s) = SHAPING_GAIN * (WAY_MAX - way_to_goal(s))

with ``Phi = 0`` after a terminal step (what invariance in an episodic task needs). The way to the goal
(``way_to_goal``) is the potential-field controller's: beside the shelves, to the aisle mouth and on from
there to the middle of the goal line; in the aisle, straight to it. Every metre of way made good earns about
``SHAPING_GAIN``, so a policy that drives towards the gap is paid before it ever gets through.

The offset ``WAY_MAX`` (longer than any way in the arena) makes every live state's potential higher than a
terminal state's 0, so a collision forfeits the potential gathered so far. Without it (``Phi = -way``) a
crash would land on the goal's potential: crashing at once would collect the whole way in one step, and the
crash-early trap (a collision at once costs less than wandering) keeps its pull. Measured: TD3 from scratch
fell into it with ``Phi = -way``. The offset changes the shaping term by a constant potential, which
leaves the optimal policy unchanged as well.
"""

from __future__ import annotations

import math
from collections.abc import Sequence

import numpy as np

from embedrl.train import layout
from embedrl.train.robot import ROBOT_LENGTH, ROBOT_WIDTH
from embedrl.train.world import Pose, robot_corners

REWARDS = ("thesis", "potential-field", "shaped")
SUCCESS_BONUS = 5.0
"""Reward for passing the goal line (the study's two-robot runs also tried 20)."""
COLLISION_PENALTY = 2.0
LIVING_COST = 0.14
CONTOUR_GAIN = 0.05
"""Depth of an obstacle's contour: what a point on the obstacle loses."""
CONTOUR_RANGE = 0.05
"""Decay length of an obstacle's contour [m]."""


def check_options(reward: str, success_bonus: float, shaping_gain: float = 1.0) -> None:
    """The envs' reward arguments: a known reward, a finite, non-negative success bonus and shaping gain
    (ValueError)."""
    if reward not in REWARDS:
        raise ValueError(f"reward {reward!r} is not one of {', '.join(REWARDS)}")
    for name, value in (("success_bonus", success_bonus), ("shaping_gain", shaping_gain)):
        if not (math.isfinite(value) and value >= 0):
            raise ValueError(f"{name} must be a finite number >= 0, got {value}")


def step_costs(w: float, action: np.ndarray) -> float:
    """The study's per-step terms that do not depend on the position: living, turning and effort."""
    return -LIVING_COST - 0.001 * w * w - 0.01 * float(action[0] ** 2 + action[1] ** 2)


def thesis(
    x: float,
    y: float,
    w: float,
    action: np.ndarray,
    made_it: bool,
    collided: bool,
    bonus: float = SUCCESS_BONUS,
) -> float:
    """The reference study's reward (eq. 19) for one step, on the state after the step."""
    return float(
        0.06 * math.exp(-3.0 * y)
        + 0.05 * math.exp(-8.0 * x * x)
        - LIVING_COST
        - 0.001 * w * w
        - 0.01 * float(action[0] ** 2 + action[1] ** 2)
        + bonus * made_it
        - COLLISION_PENALTY * collided
    )


def robot_distance(px: float, py: float, pose: Pose) -> float:
    """Distance from a point to a robot body at ``pose`` (0 inside it)."""
    x, y, theta = pose
    c, s = math.cos(theta), math.sin(theta)
    lx = c * (px - x) + s * (py - y)
    ly = -s * (px - x) + c * (py - y)
    dx = max(abs(lx) - ROBOT_LENGTH / 2, 0.0)
    dy = max(abs(ly) - ROBOT_WIDTH / 2, 0.0)
    return math.hypot(dx, dy)


def field(px: float, py: float, obstacles: Sequence[layout.Rect], others: Sequence[Pose] = ()) -> float:
    """The potential-field reward's position term at a point: the study's attraction minus contours."""
    total = 0.06 * math.exp(-3.0 * py) + 0.05 * math.exp(-8.0 * px * px)
    for rect in obstacles:
        total -= CONTOUR_GAIN * math.exp(-rect.distance(px, py)[0] / CONTOUR_RANGE)
    for pose in others:
        total -= CONTOUR_GAIN * math.exp(-robot_distance(px, py, pose) / CONTOUR_RANGE)
    return total


def potential_field(
    pose: Pose,
    w: float,
    action: np.ndarray,
    made_it: bool,
    collided: bool,
    obstacles: Sequence[layout.Rect],
    others: Sequence[Pose] = (),
    bonus: float = SUCCESS_BONUS,
) -> float:
    """The potential-field reward for one step: the field averaged over the four corners at ``pose``."""
    corners = robot_corners(*pose)
    position = sum(field(cx, cy, obstacles, others) for cx, cy in corners) / len(corners)
    return float(position + step_costs(w, action) + bonus * made_it - COLLISION_PENALTY * collided)


SHAPING_GAIN = 1.0
"""Potential per metre of way to the goal (the way from a start is 1.6-2.1 m)."""
WAY_MAX = 3.0
"""Offset of the potential [m]: longer than the way from anywhere in the arena (at most 2.93 m)."""
SHAPING_GAMMA = 0.99
"""The default discount of the shaping term; invariance needs the agent's own, which training passes
(the envs' ``shaping_gamma``)."""
MOUTH_X = layout.UPPER_SHELF_WIDTH / 2 + 0.15
"""|x| of the aisle mouth, where the way from beside the shelves enters the aisle [m]."""
MOUTH_Y = 0.32
"""Height of the aisle mouth [m]."""


def way_to_goal(x: float, y: float) -> float:
    """Length of the way from (x, y) to the middle of the goal line [m]: via the aisle mouth from beside
    the shelves, straight from inside the aisle."""
    if abs(x) < MOUTH_X and y < layout.AISLE_WIDTH:
        return math.hypot(x, y - layout.GOAL_Y)
    mouth = math.copysign(MOUTH_X, x)
    return math.hypot(x - mouth, y - MOUTH_Y) + math.hypot(MOUTH_X, MOUTH_Y - layout.GOAL_Y)


def potential(x: float, y: float, gain: float = SHAPING_GAIN) -> float:
    """The shaping potential ``Phi`` of a non-terminal state (positive everywhere in the arena)."""
    return gain * (WAY_MAX - way_to_goal(x, y))


def shaping(phi_before: float, phi_after: float, terminal: bool, gamma: float = SHAPING_GAMMA) -> float:
    """The shaping term ``gamma * Phi(s') - Phi(s)``, with ``Phi(s') = 0`` when the step ended the episode."""
    return gamma * (0.0 if terminal else phi_after) - phi_before
