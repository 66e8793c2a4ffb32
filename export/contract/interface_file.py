"""An export's ``interface.json``, read as untrusted input: validated into an :class:`Interface`."""

from __future__ import annotations

from pathlib import Path

from embedrl.common import read_json
from embedrl.export.contract.errors import ContractError
from embedrl.train.interface import Interface


def load_interface(path: Path) -> Interface:
    """The interface in ``path`` (an export's ``interface.json``); :class:`ContractError` naming the file
    if it cannot be read or does not describe a deployable policy."""
    try:
        return Interface.from_json(read_json(path))
    except (OSError, ValueError) as exc:
        raise ContractError(f"{path}: {exc}") from None
