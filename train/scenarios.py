"""The scenarios' interface specs: one :class:`~train.interface.Interface` per scenario.

Everything that crosses the boundary between the simulator and a deployed policy is derived from these:
the env's spaces and docstring tables, an export's ONNX metadata and ``policy.h`` constants, the CAN
database and the HIL harness's mapping.
"""

from __future__ import annotations

from typing import Any

from gymnasium import spaces
from gymnasium.envs.registration import load_env_creator

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

MOVING_SHELF_ENV_ID = "embedrl/WarehouseMovingShelf-v0"
_SHELF_DX = layout.ARENA_HALF_WIDTH + layout.MOVING_SHELF_WRAP_X
_SHELF_FIELDS = (
    Field("shelf_dx", "moving shelf centre x minus robot x", -_SHELF_DX, _SHELF_DX, "m"),
    Field(
        "shelf_dy",
        "moving shelf lower edge y minus robot y",
        layout.MOVING_SHELF_Y_MIN - layout.ARENA_TOP,
        layout.MOVING_SHELF_Y_MAX - layout.GOAL_Y,
        "m",
    ),
    Field(
        "shelf_vx",
        "moving shelf velocity along x",
        -layout.MOVING_SHELF_SPEED_MAX,
        layout.MOVING_SHELF_SPEED_MAX,
        "m/s",
    ),
)

MOVING_SHELF = Interface(
    name="moving-shelf",
    env_id=MOVING_SHELF_ENV_ID,
    observation=STATIC.observation + _SHELF_FIELDS,
    action=STATIC.action,
    sample_time_s=SAMPLE_TIME,
    safe_action=STATIC.safe_action,
    max_steps=STATIC.max_steps,
)
"""The study's changing environment: the upper shelf moves along the aisle
(``embedrl/WarehouseMovingShelf-v0``); the robot also observes where the shelf is and how fast it moves."""

MOVING_SHELF_PARTIAL_ENV_ID = "embedrl/WarehouseMovingShelfPartial-v0"

MOVING_SHELF_PARTIAL = Interface(
    name="moving-shelf-partial",
    env_id=MOVING_SHELF_PARTIAL_ENV_ID,
    observation=STATIC.observation + tuple(f for f in _SHELF_FIELDS if f.name != "shelf_vx"),
    action=STATIC.action,
    sample_time_s=SAMPLE_TIME,
    safe_action=STATIC.safe_action,
    max_steps=STATIC.max_steps,
)
"""The moving shelf, partially observed: where the shelf is, not how fast or which way it moves
(``embedrl/WarehouseMovingShelfPartial-v0``). One observation cannot tell the shelf's direction; a policy
with memory can, from two."""

TWO_ROBOTS_ENV_ID = "embedrl/WarehouseTwoRobots-v0"
_SPAN_X = 2 * layout.ARENA_HALF_WIDTH
_SPAN_Y = layout.ARENA_TOP - layout.GOAL_Y
_OTHER_FIELDS = (
    Field("other_dx", "other robot x minus own x", -_SPAN_X, _SPAN_X, "m"),
    Field("other_dy", "other robot y minus own y", -_SPAN_Y, _SPAN_Y, "m"),
    Field("other_sin_theta", "other robot sin(theta)", -1.0, 1.0),
    Field("other_cos_theta", "other robot cos(theta)", -1.0, 1.0),
    Field("other_speed", "other robot forward speed", -MAX_SPEED, MAX_SPEED, "m/s"),
    Field("other_present", "1 while the other robot is in the arena, else 0", 0.0, 1.0),
)

TWO_ROBOTS = Interface(
    name="two-robots",
    env_id=TWO_ROBOTS_ENV_ID,
    observation=STATIC.observation + _OTHER_FIELDS,
    action=STATIC.action,
    sample_time_s=SAMPLE_TIME,
    safe_action=STATIC.safe_action,
    max_steps=STATIC.max_steps,
    robots=2,
)
"""The study's two robots through one gap; this is one robot's interface (each robot runs its own copy of
the policy, on its own node)."""

WALKER_ENV_ID = "embedrl/DeckWalker-v0"
MUJOCO_TIMESTEP = 0.002
"""The physics step of gymnasium's ``walker2d_v5.xml`` [s]."""
WALKER_FRAME_SKIP = 4
"""Physics steps per control step (gymnasium's default for Walker2d-v5)."""
WALKER_SAMPLE_TIME = WALKER_FRAME_SKIP * MUJOCO_TIMESTEP
"""The walker's control period, 8 ms (a test ties it to the env's ``dt``)."""
WALKER_MAX_STEPS = 1000
"""Gymnasium's Walker2d-v5 episode: 1,000 steps, 8 s."""
HIP_KNEE_OBSERVED = (-3.2, 0.6)
"""The observed range of the thigh and knee angles [rad]: the model's limits (-150 to 0 degrees, -2.618 to 0
rad) with at least 0.5 rad to spare on each side, MuJoCo's joint limits being soft."""
FOOT_OBSERVED = (-1.3, 1.3)
"""The observed range of the foot angles [rad]: the model's limits (+-45 degrees) with 0.5 rad to spare."""
WALKER_SPEED_LIMIT = 10.0
"""Walker2d-v5 clips every velocity it observes to +-10 (m/s, rad/s)."""
_JOINTS = (("thigh", "right thigh"), ("leg", "right knee"), ("foot", "right foot"),
           ("thigh_left", "left thigh"), ("leg_left", "left knee"), ("foot_left", "left foot"))  # fmt: skip


def _joint_angle(name: str, text: str) -> Field:
    low, high = FOOT_OBSERVED if name.startswith("foot") else HIP_KNEE_OBSERVED
    return Field(f"{name}_angle", f"{text} joint angle", low, high, "rad")


def _rate(name: str, text: str, unit: str = "rad/s") -> Field:
    return Field(name, text, -WALKER_SPEED_LIMIT, WALKER_SPEED_LIMIT, unit)


WALKER = Interface(
    name="walker",
    env_id=WALKER_ENV_ID,
    observation=(
        Field("torso_z", "trunk height", 0.0, 2.5, "m"),
        Field("torso_angle", "trunk pitch (0 = upright)", -2.0, 2.0, "rad"),
        *(_joint_angle(name, text) for name, text in _JOINTS),
        _rate("vel_x", "trunk forward velocity", "m/s"),
        _rate("vel_z", "trunk vertical velocity", "m/s"),
        _rate("torso_rate", "trunk pitch rate"),
        *(_rate(f"{name}_rate", f"{text} joint rate") for name, text in _JOINTS),
    ),
    action=tuple(Field(f"{name}_torque", f"{text} motor torque", -1.0, 1.0) for name, text in _JOINTS),
    sample_time_s=WALKER_SAMPLE_TIME,
    safe_action=(0.0,) * len(_JOINTS),
    max_steps=WALKER_MAX_STEPS,
)
"""The slide deck's walking robot: gymnasium's MuJoCo Walker2d-v5 (planar, six actuated joints) with the
deck's reward (``embedrl/DeckWalker-v0``). The safe action is no torque: the walker then sinks to the
ground."""

SCENARIOS = {spec.name: spec for spec in (STATIC, MOVING_SHELF, TWO_ROBOTS, MOVING_SHELF_PARTIAL, WALKER)}
"""Every scenario by name, the first the default; names, observation sizes and help come from here."""
BY_ENV_ID = {spec.env_id: spec for spec in SCENARIOS.values()}
DEFAULT_SCENARIO = STATIC.name
SUMMARIES = {
    STATIC.name: "one robot, three fixed shelves",
    MOVING_SHELF.name: "the upper shelf moves along the aisle",
    TWO_ROBOTS.name: "two robots through one gap, one policy drives both",
    MOVING_SHELF_PARTIAL.name: "the moving shelf seen without its velocity (memory needed)",
    WALKER.name: "the deck's walking robot (MuJoCo Walker2d-v5, the deck's reward)",
}
"""One line per scenario, for help texts and plot titles (a test ties the keys to :data:`SCENARIOS`)."""


SHELF_FIELDS = tuple(f.name for f in _SHELF_FIELDS)
"""The moving shelf's fields (the controller reads them by name, in this order: dx, dy, vx)."""
SHELF_POSITION_FIELDS = SHELF_FIELDS[:2]
"""A scenario whose observation has these fields has the moving shelf (the plots draw it)."""
TEACHERS = {MOVING_SHELF_PARTIAL.name: MOVING_SHELF.name}
"""Scenarios whose potential-field demonstrations see more than the learner: the controller of the named
scenario drives on the env's full observation (:meth:`~train.moving_shelf_env.WarehouseMovingShelfEnv.
full_observation`), the learner records its own."""
WAREHOUSE = (STATIC.name, MOVING_SHELF.name, TWO_ROBOTS.name, MOVING_SHELF_PARTIAL.name)
"""The warehouse scenarios: the potential-field controller drives them, its demonstrations teach them."""
OTHER_ROBOT_FIELDS = ("other_dx", "other_dy", "other_present")
"""A scenario whose observation has these fields has a second robot, driven by its own copy of the policy."""
TEAM_ENVS = {TWO_ROBOTS.name: "embedrl.train.two_robots_env:WarehouseTwoRobotsEnv"}
"""The PettingZoo Parallel env of every scenario with more than one robot (``robots > 1``): all its robots
in one episode, one agent each (``possible_agents`` in robot order), and per robot its ``outcomes`` and
``trajectories`` (as :class:`~train.two_robots_env.WarehouseTwoRobotsEnv`). Training, evaluation and HIL
drive it; the gymnasium env registered under the spec's ``env_id`` is one robot's seat, the others driven by
a ``partner``."""


def team_env(spec: Interface, **kwargs: Any) -> Any:
    """A new team env of ``spec``'s scenario (:data:`TEAM_ENVS`), built with ``kwargs``."""
    return load_env_creator(TEAM_ENVS[spec.name])(**kwargs)


def field_indices(spec: Interface, names: tuple[str, ...]) -> tuple[int, ...] | None:
    """Where ``names`` sit in the spec's observation, or None if any is missing."""
    index = {f.name: i for i, f in enumerate(spec.observation)}
    return tuple(index[n] for n in names) if all(n in index for n in names) else None


def has_moving_shelf(env_id: str) -> bool:
    """Whether the scenario of ``env_id`` has the moving shelf (False for an env without a spec)."""
    spec = BY_ENV_ID.get(env_id)
    return spec is not None and field_indices(spec, SHELF_POSITION_FIELDS) is not None


def scenario_help() -> str:
    """The scenarios as a command's help lists them: name, observation size and what happens."""
    return "; ".join(
        f"{name}: {SUMMARIES[name]}, {len(spec.observation)} observations" for name, spec in SCENARIOS.items()
    )


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
