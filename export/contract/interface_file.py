"""An export's ``interface.json``, read as untrusted input: validated into an :class:`Interface`."""

from __future__ import annotations

from dataclasses import replace
from pathlib import Path

from embedrl.common import read_json
from embedrl.export.contract.errors import ContractError
from embedrl.train.interface import Interface
from embedrl.train.scenarios import BY_ENV_ID


def load_interface(path: Path) -> Interface:
    """The interface in ``path`` (an export's ``interface.json``); :class:`ContractError` naming the file
    if it cannot be read or does not describe a deployable policy. A scenario's interface gets what the file
    does not carry, the scenario's robot count (:attr:`Interface.robots`)."""
    try:
        interface = Interface.from_json(read_json(path))
    except (OSError, ValueError) as exc:
        raise ContractError(f"{path}: {exc}") from None
    scenario = BY_ENV_ID.get(interface.env_id)
    return interface if scenario is None else replace(interface, robots=scenario.robots)
