"""The report's layer table counts each weight array once, as a Cortex-M target compiles it, so its total
agrees with the generated header's count in every precision (the host's own layouts left out)."""

from __future__ import annotations

import re
from pathlib import Path

import pytest

from embedrl.hil.signoff.layers import const_arrays
from tests.conftest import Exported

SHIPPED_TD3 = Path(__file__).resolve().parents[2] / "policies" / "static" / "td3.zip"


@pytest.mark.parametrize("precision", ["float32", "int8", "int8-weights", "q15"])
def test_the_weight_arrays_add_up_to_the_headers_count(exported: Exported, precision: str) -> None:
    flags = ("--episodes", "0") if precision == "float32" else ("--episodes", "0", "--quantize", precision)
    c_dir = exported(SHIPPED_TD3, *flags) / "c"
    source = (c_dir / "policy.c").read_text()
    header = re.search(r"weights: (\d+) bytes of const data", (c_dir / "policy.h").read_text())
    assert header
    arrays = const_arrays(source, "policy")
    assert sum(size for _, size in arrays) == int(header.group(1))
    if precision in (
        "float32",
        "int8",
    ):  # these hold a second layout of the weights for one build or the other
        assert re.search(r"^#if (defined\(__x86_64__\)|!\(defined\(__ARM_ARCH_PROFILE\))", source, re.M)
