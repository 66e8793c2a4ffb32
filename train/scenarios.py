"""The scenarios' interface specs: one :class:`~train.interface.Interface` per scenario.

Everything that crosses the boundary between the simulator and a deployed policy is derived from these:
the env's spaces and docstring tables, an export's ONNX metadata and ``policy.h`` constants, the CAN
database and the HIL harness's mapping.
"""

from __future__ import annotations

from typing import Any

from gymnasium import spaces

from embedrl.train import layout
from embedrl.train.interface import Field, Interface, InterfaceError, from_spaces
from embedrl.train.robot import MAX_SPEED, MAX_TURN_RATE, SAMPLE_TIME

STATIC_ENV_ID = "embedrl/WarehouseRobot-v0"
GENERIC_MAX_STEPS = 1000

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


def interface_of(env_id: str, env: Any) -> Interface:
    """The spec of a scenario's env, or a generic interface derived from another env's Box spaces.

    A generic interface takes its sample time from the env's ``dt`` (or ``1 / render_fps``) and its
    step limit from the registration (1,000 if none).
    """
    if env_id in BY_ENV_ID:
        return BY_ENV_ID[env_id]
    obs, act = env.observation_space, env.action_space
    if not (isinstance(obs, spaces.Box) and isinstance(act, spaces.Box)):
        raise InterfaceError(
            f"{env_id}: only Box observation and action spaces can be deployed, got {obs}, {act}"
        )
    dt = getattr(env.unwrapped, "dt", None)
    fps = env.metadata.get("render_fps")
    sample_time = float(dt) if dt else 1.0 / float(fps) if fps else None
    if sample_time is None or not sample_time > 0:
        raise InterfaceError(f"{env_id}: cannot tell its sample time (no dt and no render_fps)")
    spec = getattr(env, "spec", None)
    max_steps = spec.max_episode_steps if spec is not None and spec.max_episode_steps else GENERIC_MAX_STEPS
    return from_spaces(
        env_id, obs.low.reshape(-1), obs.high.reshape(-1), act.low.reshape(-1), act.high.reshape(-1),
        sample_time, int(max_steps),
    )  # fmt: skip
