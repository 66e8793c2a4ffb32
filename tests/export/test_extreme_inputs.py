"""Extreme observations into the generated C, in float32, int8-weights, q15 and int8, under UBSan and ASan.

Every finite or non-finite input: no sanitizer report (the process aborts on the first), a non-finite
observation returns POLICY_ERR_OBS_NOT_FINITE with the export's safe action, and a finite one returns an
action inside the action space (the export bounds or clamps its actions), or, where the network itself
overflows (observations beyond about 1e35 in float arithmetic), POLICY_ERR_ACT_NOT_FINITE with the safe
action: a defined result either way.
"""

from __future__ import annotations

import subprocess
from pathlib import Path

import numpy as np
import pytest

from tests.conftest import Exported

SHIPPED_TD3 = Path(__file__).resolve().parents[2] / "policies" / "static" / "td3.zip"
DRIVER = Path(__file__).with_name("c") / "extreme_driver.c"
F32 = np.finfo(np.float32)
SPECIAL = np.array(
    [0.0, -0.0, 1.0, -1.0, F32.smallest_subnormal, -F32.smallest_subnormal, F32.tiny, -F32.tiny,
     1e-30, -1e-30, 1e30, -1e30, 65504.0, -32769.0, F32.max, -F32.max, np.inf, -np.inf, np.nan],
    dtype=np.float32,
)  # fmt: skip
OBS_DIM, ACT_DIM = 6, 2
OBS_NOT_FINITE, ACT_NOT_FINITE = 1, 2
OVERFLOW_BOUND = 1e30
"""Observations below this magnitude never overflow the shipped network (measured: 9.5e35 at the least)."""


def extreme_observations(seed: int = 0) -> np.ndarray:
    """Each special value in each position (others 0), random mixes of them, and random bit patterns."""
    rng = np.random.default_rng(seed)
    single = np.zeros((len(SPECIAL) * OBS_DIM, OBS_DIM), dtype=np.float32)
    for k, value in enumerate(SPECIAL):
        for i in range(OBS_DIM):
            single[k * OBS_DIM + i, i] = value
    mixes = rng.choice(SPECIAL, size=(3000, OBS_DIM))
    bits = rng.integers(0, 2**32, size=(3000, OBS_DIM), dtype=np.uint64).astype(np.uint32).view(np.float32)
    return np.concatenate([single, mixes, bits]).astype(np.float32)


@pytest.fixture(scope="module", params=["float32", "int8-weights", "q15", "int8"])
def sanitized_policy(
    request: pytest.FixtureRequest, tmp_path_factory: pytest.TempPathFactory, exported: Exported
) -> Path:
    quantize = [] if request.param == "float32" else ["--quantize", request.param]
    out = exported(SHIPPED_TD3, "--episodes", "0", *quantize)
    binary = tmp_path_factory.mktemp(request.param) / "extreme"
    subprocess.run(
        ["cc", "-std=c99", "-O1", "-g", "-fsanitize=undefined,address", "-fno-sanitize-recover=all",
         "-I", str(out / "c"), "-o", str(binary), str(DRIVER), str(out / "c" / "policy.c"), "-lm"],
        check=True,
    )  # fmt: skip
    return binary


@pytest.mark.slow
def test_extreme_inputs_never_trip_a_sanitizer_and_give_defined_results(sanitized_policy: Path) -> None:
    obs = extreme_observations()
    result = subprocess.run([str(sanitized_policy)], input=obs.tobytes(), capture_output=True, timeout=300)
    assert result.returncode == 0 and not result.stderr, result.stderr.decode()[-2000:]
    records = np.frombuffer(result.stdout, dtype=np.dtype([("code", "<i4"), ("act", "<f4", ACT_DIM)]))
    assert len(records) == len(obs)
    finite = np.all(np.isfinite(obs), axis=1)
    assert np.all(records["code"][~finite] == OBS_NOT_FINITE)
    assert np.all(records["act"][~finite] == 0.0)  # the export's safe action (0, 0)
    ok = finite & (records["code"] == 0)
    overflow = finite & (records["code"] == ACT_NOT_FINITE)
    assert np.all(ok | overflow | ~finite)
    assert np.all(np.isfinite(records["act"][ok])) and np.all(np.abs(records["act"][ok]) <= 1.0)
    assert np.all(records["act"][overflow] == 0.0)
    assert np.all(np.abs(obs[overflow]).max(axis=1) > OVERFLOW_BOUND)
