"""Numbers as generated text: C float literals that round-trip the float32 value, and DBC limits."""

from __future__ import annotations

import numpy as np

from embedrl.export.contract.errors import ContractError


def c_float(value: float) -> str:
    """A C float literal that round-trips the float32 value exactly (9 significant digits)."""
    v = np.float32(value)
    if not np.isfinite(v):
        raise ContractError(f"cannot write non-finite constant {value!r} as C")
    text = f"{float(v):.9g}"
    if not any(c in text for c in ".en"):
        text += ".0"
    return text + "f"


def dbc_number(value: float) -> float:
    """9 significant digits: the float32 value the env sends, written without binary noise."""
    return float(f"{value:.9g}")
