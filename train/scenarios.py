"""The scenarios' interface specs: one :class:`~train.interface.Interface` per scenario.

Everything that crosses the boundary between the simulator and a deployed policy is derived from these:
the env's spaces and docstring tables, an export's ONNX metadata and ``policy.h`` constants, the CAN
database and the HIL harness's mapping.
"""

from __future__ import annotations

from train import layout
from train.interface import Field, Interface
from train.robot import MAX_SPEED, MAX_TURN_RATE, SAMPLE_TIME

STATIC_ENV_ID = "embedrl/WarehouseRobot-v0"

STATIC = Interface(
    name="static",
    env_id=STATIC_ENV_ID,
    observation=(
        Field("x", "x, position along the shelves", -layout.ARENA_HALF_WIDTH, layout.ARENA_HALF_WIDTH, "m"),
        Field("y", "y, position across the shelves", layout.GOAL_Y, layout.ARENA_TOP, "m"),
        Field("sin_theta", "sin(theta), heading (0 = along +x)", -1.0, 1.0),
        Field("cos_theta", "cos(theta)", -1.0, 1.0),
        Field("speed", "v, forward speed", -MAX_SPEED, MAX_SPEED, "m/s"),
        Field("turn_rate", "w, turn rate (counter-clockwise)", -MAX_TURN_RATE, MAX_TURN_RATE, "rad/s"),
    ),
    action=(
        Field("force_left", "left wheel force ``F_L``", -1.0, 1.0),
        Field("force_right", "right wheel force ``F_R``", -1.0, 1.0),
    ),
    sample_time_s=SAMPLE_TIME,
    safe_action=(0.0, 0.0),
    max_steps=200,
)
"""The study's static scenario: one robot, three fixed shelves (``embedrl/WarehouseRobot-v0``)."""

SCENARIOS = {STATIC.name: STATIC}
BY_ENV_ID = {spec.env_id: spec for spec in SCENARIOS.values()}
