"""The scenario spec is the contract: the env's spaces and docstring tables agree with it, and an
interface description is validated like any untrusted input."""

from __future__ import annotations

import json
import re

import gymnasium as gym
import numpy as np
import pytest

from embedrl import train
from embedrl.train.interface import Field, Interface, InterfaceError, from_spaces
from embedrl.train.moving_shelf_env import WarehouseMovingShelfEnv
from embedrl.train.scenarios import BY_ENV_ID, MOVING_SHELF, SCENARIOS, STATIC, TWO_ROBOTS
from embedrl.train.two_robots_env import WarehouseTwoRobotsEnv
from embedrl.train.warehouse_env import WarehouseRobotEnv

ROW = re.compile(r"^\s*\|\s*(\d+)\s*\|(.*)\|\s*$")


def _table(doc: str, heading: str) -> list[list[str]]:
    """The rows of the markdown table under ``## heading`` in a docstring (without the header)."""
    section = doc.split(f"## {heading}", 1)[1].split("##", 1)[0]
    rows = []
    for line in section.splitlines():
        match = ROW.match(line)
        if match:
            rows.append([match.group(1), *(cell.strip() for cell in match.group(2).split("|"))])
    return rows


def test_the_env_spaces_come_from_the_spec() -> None:
    env = gym.make(train.ENV_ID)
    assert isinstance(env.observation_space, gym.spaces.Box) and isinstance(env.action_space, gym.spaces.Box)
    np.testing.assert_array_equal(env.observation_space.low, STATIC.obs_low)
    np.testing.assert_array_equal(env.observation_space.high, STATIC.obs_high)
    np.testing.assert_array_equal(env.action_space.low, STATIC.act_low)
    np.testing.assert_array_equal(env.action_space.high, STATIC.act_high)
    assert env.spec is not None and env.spec.max_episode_steps == STATIC.max_steps
    assert BY_ENV_ID[train.ENV_ID] is STATIC and SCENARIOS["static"] is STATIC


@pytest.mark.parametrize(
    ("doc", "spec"),
    [
        (WarehouseRobotEnv.__doc__, STATIC),
        (WarehouseMovingShelfEnv.__doc__, MOVING_SHELF),
        (WarehouseTwoRobotsEnv.__doc__, TWO_ROBOTS),
    ],
    ids=["static", "moving-shelf", "two-robots"],
)
def test_the_docstring_tables_match_the_spec(doc: str | None, spec: Interface) -> None:
    doc = doc or ""
    observations = _table(doc, "Observation Space")
    assert len(observations) == len(spec.observation)
    for (num, description, low, high, unit), field in zip(observations, spec.observation, strict=True):
        assert description == field.description, f"row {num}"
        assert float(low) == pytest.approx(field.low, abs=1e-9) and float(high) == pytest.approx(field.high)
        assert unit == field.unit
    actions = _table(doc, "Action Space")
    assert len(actions) == len(spec.action)
    for (_, description, low, high), field in zip(actions, spec.action, strict=True):
        assert (description, float(low), float(high)) == (field.description, field.low, field.high)
    assert f"{spec.max_steps} steps" in doc and f"({spec.sample_time_s} s)" in doc


def test_json_round_trip_is_exact_and_canonical() -> None:
    text = STATIC.dumps()
    assert Interface.from_json(json.loads(text)) == STATIC
    assert text == STATIC.dumps() and json.loads(text)["format"] == 1


@pytest.mark.parametrize(
    ("change", "message"),
    [
        ({"observation": (Field("X", "", 0, 1),)}, "is not a lower-case identifier"),
        ({"observation": (Field("a", "", 1, 1),)}, "needs finite low < high"),
        ({"observation": (Field("a", "", 0, float("inf")),)}, "needs finite low < high"),
        ({"action": (Field("a", "", 0, 1), Field("a", "", 0, 1))}, "duplicate action field names"),
        ({"safe_action": (0.0,)}, "the safe action has 1 values for 2 actions"),
        ({"safe_action": (1.5, 0.0)}, "safe action force_left=1.5 is outside [-1.0, 1.0]"),
        ({"sample_time_s": 0.0}, "must be positive"),
    ],
)
def test_an_inconsistent_interface_is_rejected(change: dict[str, object], message: str) -> None:
    fields = {k: getattr(STATIC, k) for k in Interface.__dataclass_fields__}
    with pytest.raises(InterfaceError, match=re.escape(message)):
        Interface(**{**fields, **change})


@pytest.mark.parametrize(
    "data",
    [{}, {"format": 2}, {"format": 1, "name": "x"}, [], {**STATIC.to_json(), "observation": [{"name": 3}]}],
)
def test_a_bad_interface_file_is_a_clear_error(data: object) -> None:
    with pytest.raises(InterfaceError):
        Interface.from_json(data)


def test_an_env_without_a_spec_gets_generic_fields() -> None:
    spec = from_spaces(
        "Pendulum-v1",
        np.array([-1, -1, -8.0]),
        np.array([1, 1, 8.0]),
        np.array([-2.0]),
        np.array([2.0]),
        0.05,
        200,
    )
    assert [f.name for f in spec.observation] == ["obs0", "obs1", "obs2"]
    assert spec.action[0].name == "act0" and spec.safe_action == (0.0,)
    assert STATIC.with_safe_action((0.1, 0.0)).safe_action == (0.1, 0.0)
    with pytest.raises(InterfaceError):
        STATIC.with_safe_action((2.0, 0.0))
