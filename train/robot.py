"""The warehouse robot: its body, wheels and friction, and the control period.

Shared by every warehouse scenario; the scenario specs (:mod:`train.scenarios`) derive the bounds of
the speed and turn-rate observations from these constants.
"""

from __future__ import annotations

SAMPLE_TIME = 0.3
"""Control period [s]: one env step holds the wheel forces for this long."""
PHYSICS_SUBSTEPS = 6
"""pymunk steps per env step (0.05 s each): the robot moves at most 3.5 cm per physics
step, well under the 0.1 m thinnest obstacle, so no contact is missed."""
ROBOT_LENGTH = 0.25
"""Robot body length along its heading [m]."""
ROBOT_WIDTH = 0.2
"""Robot body width [m]; the wheels sit on its sides."""
ROBOT_MASS = 10.0
"""[kg]"""
WHEEL_HALF_TRACK = ROBOT_WIDTH / 2
"""Distance of each wheel from the centre line [m]."""
WHEEL_FORCE_SCALE = 28.0
"""Force [N] per unit action: each wheel pushes ``WHEEL_FORCE_SCALE * a / 2``, so the
translational force is ``WHEEL_FORCE_SCALE * (F_R + F_L) / 2`` and the torque is
``WHEEL_FORCE_SCALE * WHEEL_HALF_TRACK * (F_R - F_L) / 2``."""
LINEAR_FRICTION = 40.0
"""Rolling friction along the heading [N per m/s]: top speed 0.7 m/s, time constant 0.25 s.
Sideways the wheels do not slip: the lateral velocity is removed every physics step."""
ANGULAR_FRICTION = 1.4
"""Rotational friction [N m per rad/s]: top turn rate 2.0 rad/s."""

MAX_SPEED = WHEEL_FORCE_SCALE / LINEAR_FRICTION
"""Terminal forward speed at full force [m/s]; the bound of observation ``v``."""
MAX_TURN_RATE = WHEEL_FORCE_SCALE * WHEEL_HALF_TRACK / ANGULAR_FRICTION
"""Terminal turn rate at full differential force [rad/s]; the bound of observation ``w``."""
