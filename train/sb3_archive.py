"""Reading a Stable-Baselines3 ``.zip`` without running anything from it.

SB3 stores some fields of its ``data`` entry as pickles (``:serialized:``); unpickling a file from
someone else can run arbitrary code. This module reads only what export and evaluation need, from the
readable copies SB3 writes beside each pickle, and never unpickles:

- the policy class: the pickle of a class is a reference (module and name); it is decoded statically with
  :mod:`pickletools` (no opcode is executed) and accepted only if it is one of :data:`POLICY_CLASSES`;
- the observation and action spaces: ``Box`` from its readable ``dtype``, ``_shape``, ``low`` and ``high``;
- ``policy_kwargs``: Python literals, and activation functions from :data:`ACTIVATIONS` by name;
- the network parameters: SB3 reads ``policy.pth`` with ``torch.load(weights_only=True)``, which refuses
  anything but tensors.

Anything else (a pickle that is more than a class reference, an unknown class or keyword, a summarised
array) is refused with a message that names the field; ``trust_pickle`` loads with SB3's own (unpickling)
reader instead, for files the user trusts.
"""

from __future__ import annotations

import ast
import base64
import pickletools
import re
import zipfile
from pathlib import Path
from typing import Any

import numpy as np
from gymnasium import spaces
from torch import nn

from embedrl.common import parse_json
from embedrl.train.errors import InvalidModelFileError, UnsupportedModelFileError

POLICY_CLASSES = {
    ("stable_baselines3.td3.policies", "TD3Policy"),
    ("stable_baselines3.td3.policies", "MlpPolicy"),
    ("stable_baselines3.sac.policies", "SACPolicy"),
    ("stable_baselines3.sac.policies", "MlpPolicy"),
    ("stable_baselines3.common.policies", "ActorCriticPolicy"),
    ("stable_baselines3.ppo.policies", "MlpPolicy"),
    ("stable_baselines3.a2c.policies", "MlpPolicy"),
    ("embedrl.train.study_agents", "StudyTD3Policy"),
    ("embedrl.train.study_agents", "StudySACPolicy"),
    ("embedrl.train.study_agents", "SoftplusActorCriticPolicy"),
    ("sb3_contrib.common.recurrent.policies", "RecurrentActorCriticPolicy"),
    ("sb3_contrib.ppo_recurrent.policies", "MlpLstmPolicy"),
}
"""(module, name) of the policy classes an archive may name."""
ACTIVATIONS: dict[str, type[nn.Module]] = {
    f"<class 'torch.nn.modules.activation.{cls.__name__}'>": cls
    for cls in (nn.ReLU, nn.Tanh, nn.LeakyReLU, nn.Sigmoid, nn.ELU, nn.SiLU, nn.GELU)
}
"""``activation_fn`` values as SB3 writes them readably."""
CLASS_REFERENCE_OPS = frozenset(
    {
        "PROTO",
        "FRAME",
        "SHORT_BINUNICODE",
        "BINUNICODE",
        "UNICODE",
        "MEMOIZE",
        "STACK_GLOBAL",
        "GLOBAL",
        "STOP",
    }
)
"""The only opcodes in the pickle of a plain class reference."""
TRUST_HINT = "pass --trust-pickle to load it with SB3's own reader if you trust the file"


def read_data(path: Path) -> dict[str, Any]:
    """The archive's ``data`` entry as JSON (nothing unpickled)."""
    try:
        with zipfile.ZipFile(path) as archive:
            data = parse_json(archive.read("data"))
    except (zipfile.BadZipFile, KeyError, ValueError, OSError) as exc:
        raise InvalidModelFileError(f"{path}: not a readable Stable-Baselines3 model ({exc})") from None
    if not isinstance(data, dict):
        raise InvalidModelFileError(f"{path}: its data entry is not an object")
    return data


def class_reference(serialized: str) -> tuple[str, str]:
    """(module, name) that a pickled class refers to, decoded without executing the pickle."""
    try:
        ops = list(pickletools.genops(base64.b64decode(serialized)))
    except Exception as exc:
        raise ValueError(f"not a pickle ({exc})") from None
    names = [op.name for op, _, _ in ops]
    if not set(names) <= CLASS_REFERENCE_OPS:
        raise ValueError(f"not a plain class reference (opcodes {sorted(set(names) - CLASS_REFERENCE_OPS)})")
    strings = [arg for op, arg, _ in ops if op.name in ("SHORT_BINUNICODE", "BINUNICODE", "UNICODE")]
    if "STACK_GLOBAL" in names and len(strings) >= 2:
        return str(strings[-2]), str(strings[-1])
    globals_ = [arg for op, arg, _ in ops if op.name == "GLOBAL"]
    if globals_:
        module, _, name = str(globals_[0]).partition(" ")
        return module, name
    raise ValueError("no class reference")


def policy_class(path: Path, data: dict[str, Any]) -> type:
    field = data.get("policy_class")
    serialized = field.get(":serialized:") if isinstance(field, dict) else None
    if not isinstance(serialized, str):
        raise InvalidModelFileError(f"{path}: no policy_class in the archive")
    try:
        module, name = class_reference(serialized)
    except ValueError as exc:
        raise UnsupportedModelFileError(f"{path}: policy_class is {exc}; {TRUST_HINT}") from None
    if (module, name) not in POLICY_CLASSES:
        raise UnsupportedModelFileError(
            f"{path}: policy class {module}.{name} is not supported; supported: TD3Policy (TD3, DDPG), "
            "SACPolicy (SAC), ActorCriticPolicy (PPO, A2C), RecurrentActorCriticPolicy (RecurrentPPO)"
        )
    import importlib

    cls: type = getattr(importlib.import_module(module), name)
    return cls


_ARRAY = re.compile(r"^\[[-+0-9.eEinfa\s]*\]$")


def _array(
    path: Path, role: str, key: str, text: Any, dtype: np.dtype[Any], shape: tuple[int, ...]
) -> np.ndarray:
    if not isinstance(text, str) or not _ARRAY.match(text.strip()):
        raise UnsupportedModelFileError(
            f"{path}: the {role} space's {key} is not readable ({text!r}); {TRUST_HINT}"
        )
    values = np.array([float(v) for v in text.strip()[1:-1].split()], dtype=dtype)
    if values.shape != shape:
        raise UnsupportedModelFileError(
            f"{path}: the {role} space's {key} has {values.size} values for shape {shape}"
        )
    return values


def box(path: Path, data: dict[str, Any], role: str) -> spaces.Box:
    """The ``observation_space`` or ``action_space`` Box from its readable fields."""
    field = data.get(f"{role}_space")
    if not isinstance(field, dict) or field.get(":type:") != "<class 'gymnasium.spaces.box.Box'>":
        kind = field.get(":type:") if isinstance(field, dict) else type(field).__name__
        raise UnsupportedModelFileError(f"{path}: {role} space {kind} is not supported; need a 1-D Box")
    try:
        raw_shape = field["_shape"]
        shape = tuple(
            int(v) for v in (ast.literal_eval(raw_shape) if isinstance(raw_shape, str) else raw_shape)
        )
        dtype = np.dtype(str(field["dtype"]))
    except (KeyError, ValueError, SyntaxError, TypeError, RecursionError, MemoryError) as exc:
        raise UnsupportedModelFileError(
            f"{path}: the {role} space is not readable ({exc}); {TRUST_HINT}"
        ) from None
    if len(shape) != 1 or dtype.kind != "f":
        raise UnsupportedModelFileError(
            f"{path}: {role} space of shape {shape} ({dtype}) is not supported; need a 1-D float Box"
        )
    low = _array(path, role, "low", field.get("low"), dtype, shape)
    high = _array(path, role, "high", field.get("high"), dtype, shape)
    return spaces.Box(low, high, shape, dtype)


def _kwarg(path: Path, key: str, value: Any) -> Any:
    if not isinstance(value, str):
        return value
    if key == "activation_fn":
        if value in ACTIVATIONS:
            return ACTIVATIONS[value]
        raise UnsupportedModelFileError(
            f"{path}: activation_fn {value} is not supported; supported: {', '.join(sorted(ACTIVATIONS))}"
        )
    try:
        return ast.literal_eval(value)
    except (ValueError, SyntaxError, RecursionError, MemoryError):
        raise UnsupportedModelFileError(
            f"{path}: policy_kwargs {key}={value} is not a literal; {TRUST_HINT}"
        ) from None


def policy_kwargs(path: Path, data: dict[str, Any]) -> dict[str, Any]:
    """``policy_kwargs`` from the readable copy (or the plain JSON) of the field."""
    field = data.get("policy_kwargs", {})
    if not isinstance(field, dict):
        raise InvalidModelFileError(f"{path}: policy_kwargs is not an object")
    return {k: _kwarg(path, k, v) for k, v in field.items() if not k.startswith(":")}
