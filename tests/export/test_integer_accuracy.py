"""Full-integer int8 keeps the shipped policies' closed-loop result: on 200 episodes from seeds training
never used, the int8 C succeeds within 1 percentage point of the float policy (TD3 and SAC)."""

from __future__ import annotations

import json
from collections.abc import Callable
from pathlib import Path

import pytest

POLICIES = Path(__file__).resolve().parents[2] / "policies" / "static"
HELD_OUT_SEED = 1000
"""The closed loop's first episode seed: training seeds its environments with 1 (policies/static/*.json)."""
EPISODES = 200
MAX_GAP_PP = 1.0
"""How far the int8 success rate may be from the float policy's, in percentage points."""

pytestmark = pytest.mark.slow


@pytest.mark.parametrize("algo", ["td3", "sac"])
def test_int8_full_keeps_the_closed_loop_within_one_point_on_held_out_seeds(
    algo: str, exported: Callable[..., Path]
) -> None:
    out = exported(POLICIES / f"{algo}.zip", "--quantize", "int8", "--seed", str(HELD_OUT_SEED),
                   "--episodes", str(EPISODES))  # fmt: skip
    report = json.loads((out / "export_report.json").read_text())
    loop = report["closed_loop"]
    assert loop["episodes"] == EPISODES and loop["seed"] == HELD_OUT_SEED
    float_rate, int_rate = (100 * loop[who]["success_rate"] for who in ("reference", "c"))
    assert abs(float_rate - int_rate) <= MAX_GAP_PP, (float_rate, int_rate)
    assert float_rate >= 95.0  # the float policy itself is good: the comparison means something
    assert report["verification"]["quantization"]["model_mismatches"] == 0
