"""A policy's interface: its observation and action fields in order, their ranges, timing, safe action.

One :class:`Interface` per scenario is the single source of the contract between the simulator and a
deployed policy. The env's spaces, the env docstring's tables (checked by a test), the ONNX metadata and
the named constants of an export, the CAN database and the HIL harness's mapping are all derived from it.
For an environment without a spec, :func:`from_spaces` derives a generic one (fields ``obs0, obs1, ...``).
"""

from __future__ import annotations

import json
import math
import re
from dataclasses import asdict, dataclass, replace
from typing import Any

import numpy as np

NAME = re.compile(r"[a-z][a-z0-9_]*")
"""Field names are lower-case identifiers: they become C macros and CAN signal names."""
SCENARIO_NAME = re.compile(r"[A-Za-z0-9][A-Za-z0-9_.-]{0,63}")
"""An interface's ``name``: a scenario's name, or the last part of an env id."""
ENV_ID = re.compile(r"([A-Za-z0-9][A-Za-z0-9_./-]{0,99})?")
"""An ``env_id``: gymnasium's id syntax without its ``module:`` form (which would import a module)."""
TEXT = re.compile(r"[A-Za-z0-9 _()+,./=:;%'`<>^!|~@$&\[\]{}-]{0,160}")
"""A description or a unit: printable ASCII without ``*``, ``\\``, ``?``, ``#`` or ``"`` (what could end a
C comment, continue a line, form a trigraph, or end a DBC string), at most 160 characters."""
FORMAT_VERSION = 1
MAX_FIELDS = 256
"""Observation or action fields an interface may have."""
MAX_STATE_SIZE = 65_536
"""The most floats of recurrent state an interface may declare."""
INTERFACE_FILE = "interface.json"
"""An export's interface, beside its ``policy.onnx`` and ``c/``."""
NO_ENV = ""
"""``env_id`` of a policy exported without an environment (ranges given by the user): no closed loop,
HIL in open loop."""


class InterfaceError(ValueError):
    """An interface that cannot describe a deployable policy (bad names, ranges, safe action)."""


@dataclass(frozen=True)
class Field:
    """One observation or action value."""

    name: str
    """Lower-case identifier, e.g. ``sin_theta`` (C: ``POLICY_OBS_SIN_THETA``, CAN: ``SinTheta``)."""
    description: str
    low: float
    high: float
    unit: str = ""

    @property
    def camel(self) -> str:
        """The CAN signal name: ``sin_theta`` -> ``SinTheta``."""
        return "".join(part[:1].upper() + part[1:] for part in self.name.split("_"))


@dataclass(frozen=True)
class Interface:
    """The contract of a policy with its plant."""

    name: str
    """The scenario, e.g. ``static``."""
    env_id: str
    observation: tuple[Field, ...]
    action: tuple[Field, ...]
    sample_time_s: float
    """The control period: one observation in, one action out."""
    safe_action: tuple[float, ...]
    """What the deployed node applies when it cannot trust its input (watchdog, bad values)."""
    max_steps: int
    """Episodes end (truncated) after this many steps."""
    state_size: int = 0
    """Floats of recurrent state the policy carries between steps (0: none). A policy with memory gets an
    episode-start message on the bus, which resets its state."""
    robots: int = 1
    """Robots in one episode, each driven by its own copy of this policy (in HIL, each on its own node).
    A property of the scenario, not of the policy: ``interface.json`` does not carry it, and
    :func:`embedrl.export.contract.interface_file.load_interface` takes it from the scenario's spec."""

    def __post_init__(self) -> None:
        for kind, fields in (("observation", self.observation), ("action", self.action)):
            if not fields:
                raise InterfaceError(f"{self.name}: no {kind} fields")
            names = [f.name for f in fields]
            if len(set(names)) != len(names):
                raise InterfaceError(f"{self.name}: duplicate {kind} field names {names}")
            for f in fields:
                if not NAME.fullmatch(f.name):
                    raise InterfaceError(
                        f"{self.name}: {kind} field {f.name!r} is not a lower-case identifier"
                    )
                if not (math.isfinite(f.low) and math.isfinite(f.high) and f.low < f.high):
                    raise InterfaceError(
                        f"{self.name}: {kind} field {f.name} needs finite low < high, got [{f.low}, {f.high}]"
                    )
        if len(self.safe_action) != len(self.action):
            raise InterfaceError(
                f"{self.name}: the safe action has {len(self.safe_action)} values "
                f"for {len(self.action)} actions"
            )
        for f, v in zip(self.action, self.safe_action, strict=True):
            if not f.low <= v <= f.high:
                raise InterfaceError(f"{self.name}: safe action {f.name}={v} is outside [{f.low}, {f.high}]")
        if not (self.sample_time_s > 0 and self.max_steps > 0):
            raise InterfaceError(f"{self.name}: sample time and step limit must be positive")
        if not 0 <= self.state_size <= MAX_STATE_SIZE:
            raise InterfaceError(f"{self.name}: state size {self.state_size} is outside 0..{MAX_STATE_SIZE}")
        if self.robots < 1:
            raise InterfaceError(f"{self.name}: a scenario has at least one robot, got {self.robots}")

    @property
    def obs_low(self) -> np.ndarray:
        return np.array([f.low for f in self.observation], dtype=np.float32)

    @property
    def obs_high(self) -> np.ndarray:
        return np.array([f.high for f in self.observation], dtype=np.float32)

    @property
    def act_low(self) -> np.ndarray:
        return np.array([f.low for f in self.action], dtype=np.float32)

    @property
    def act_high(self) -> np.ndarray:
        return np.array([f.high for f in self.action], dtype=np.float32)

    def with_safe_action(self, safe: tuple[float, ...] | None) -> Interface:
        """This interface with another safe action (validated), or itself for ``None``."""
        if safe is None:
            return self
        return replace(self, safe_action=tuple(safe))

    def with_state_size(self, state_size: int) -> Interface:
        """This interface for a policy that carries ``state_size`` floats between steps."""
        return replace(self, state_size=state_size)

    def to_json(self) -> dict[str, Any]:
        data = asdict(self)
        del data["robots"]  # the scenario's, not the policy's
        if not self.state_size:  # a policy without memory: the same file as before memory existed
            del data["state_size"]
        return {"format": FORMAT_VERSION, **data}

    def dumps(self) -> str:
        """Canonical JSON text (sorted keys): the same interface always gives the same bytes."""
        return json.dumps(self.to_json(), indent=2, sort_keys=True) + "\n"

    @staticmethod
    def from_json(data: Any) -> Interface:
        """Parse an ``interface.json`` (untrusted: every field is checked)."""
        try:
            if data.get("format") != FORMAT_VERSION:
                raise InterfaceError(f"unsupported interface format {_shown(data.get('format'))}")
            _check_text(data)
            return Interface(
                str(data["name"]),
                str(data["env_id"]),
                tuple(_field(f) for f in data["observation"]),
                tuple(_field(f) for f in data["action"]),
                float(data["sample_time_s"]),
                tuple(float(v) for v in data["safe_action"]),
                int(data["max_steps"]),
                int(data.get("state_size", 0)),
            )
        except (AttributeError, KeyError, TypeError, ValueError) as exc:
            if isinstance(exc, InterfaceError):
                raise
            raise InterfaceError(f"not a valid interface description: {exc!r}") from None


def _shown(value: Any) -> str:
    """A value from a file, as an error message may show it: one line, bounded."""
    return repr(value)[:60].encode("ascii", "backslashreplace").decode()


def _check_text(data: dict[str, Any]) -> None:
    """The file's text fields against :data:`SCENARIO_NAME`, :data:`ENV_ID` and :data:`TEXT`: types,
    lengths and characters, before anything is built from them."""
    rules: list[tuple[str, Any, re.Pattern[str]]] = [
        ("name", data["name"], SCENARIO_NAME),
        ("env_id", data["env_id"], ENV_ID),
    ]
    for kind in ("observation", "action"):
        fields = data[kind]
        if not isinstance(fields, list) or len(fields) > MAX_FIELDS:
            raise InterfaceError(f"{kind} must be a list of at most {MAX_FIELDS} fields")
        for k, f in enumerate(fields):
            if not isinstance(f, dict):
                raise InterfaceError(f"{kind}[{k}] must be an object")
            rules += [
                (f"{kind}[{k}].name", f["name"], NAME),
                (f"{kind}[{k}].description", f["description"], TEXT),
                (f"{kind}[{k}].unit", f["unit"], TEXT),
            ]
    for where, value, pattern in rules:
        if not isinstance(value, str) or not pattern.fullmatch(value):
            raise InterfaceError(
                f"{where} {_shown(value)} is not allowed: it must match {pattern.pattern} (text in an "
                "interface becomes C comments, CAN database strings and report text)"
            )


def _field(data: Any) -> Field:
    return Field(
        str(data["name"]),
        str(data["description"]),
        float(data["low"]),
        float(data["high"]),
        str(data["unit"]),
    )


def from_spaces(
    env_id: str, obs_low: np.ndarray, obs_high: np.ndarray, act_low: np.ndarray, act_high: np.ndarray,
    sample_time_s: float, max_steps: int,
) -> Interface:  # fmt: skip
    """A generic interface for an env without a spec: fields ``obs0..``, ``act0..``, safe action at
    the middle of each action range (zero for symmetric ranges)."""
    observation = tuple(
        Field(f"obs{i}", f"observation {i}", float(lo), float(hi))
        for i, (lo, hi) in enumerate(zip(obs_low, obs_high, strict=True))
    )
    action = tuple(
        Field(f"act{i}", f"action {i}", float(lo), float(hi))
        for i, (lo, hi) in enumerate(zip(act_low, act_high, strict=True))
    )
    safe = tuple(float((lo + hi) / 2) for lo, hi in zip(act_low, act_high, strict=True))
    return Interface(env_id.split("/")[-1], env_id, observation, action, sample_time_s, safe, max_steps)


def with_names(interface: Interface, names: Any) -> Interface:
    """``interface`` with its fields renamed from ``{"observation": [...], "action": [...]}`` (a names file;
    each list as long as the fields, a name optional per list)."""
    if not isinstance(names, dict) or not set(names) <= {"observation", "action"}:
        raise InterfaceError('a names file is {"observation": [names...], "action": [names...]}')
    groups = {}
    for kind, fields in (("observation", interface.observation), ("action", interface.action)):
        given = names.get(kind)
        if given is None:
            groups[kind] = fields
            continue
        if (
            not isinstance(given, list)
            or len(given) != len(fields)
            or not all(isinstance(n, str) for n in given)
        ):
            raise InterfaceError(f"names file: {kind} must list {len(fields)} names, got {given!r}")
        groups[kind] = tuple(
            Field(n, f.description if f.description != f"{kind} {i}" else n, f.low, f.high, f.unit)
            for i, (n, f) in enumerate(zip(given, fields, strict=True))
        )
    return replace(interface, observation=groups["observation"], action=groups["action"], state_size=0)
