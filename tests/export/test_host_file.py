"""The deployable policy and its host file: ``policy.c`` holds what the firmware runs, ``policy_host.c`` the
batch entry point and the x86-64 clones for the host's verification and benchmarks; the numbers of both are
pinned to what the generator gave before the two were split (SHA-256 of the outputs, not of the text)."""

from __future__ import annotations

import ctypes
import hashlib
import re
import shlex
import subprocess
from pathlib import Path
from typing import Any

import numpy as np
import pytest

from embedrl.export import build
from embedrl.export.codegen import generate
from embedrl.export.onnx_import import to_ir
from embedrl.export.reference import OBSERVATIONS_FILE
from tests.conftest import Exported, marks_its_users
from tests.export.helpers import cpu_flags
from tests.export.test_golden import tiny_model

SHIPPED_TD3 = Path(__file__).resolve().parents[2] / "policies" / "static" / "td3.zip"
PINNED = {
    "q15": "7c16084b03d7d877e1589ef6ea5acb7f177c63214a1b950b98223ceec542e481",
    "int8-weights": "4a995f2d19594feaa6a1ecacb673ad13abb0eae032f8c9b585e7da75b8b7873a",
    "int8": "508f18abe2a87d0ae11e0e543ad67a53d28cee371864783ff0a3cc5a5b92dce0",
}
"""SHA-256 of the shipped TD3 policy's actions and return codes (float32 and int32 bytes) on its export's
verification observations plus four hostile rows (:func:`_observations`): q15's and int8-weights' by the
generator before the host file existed, int8's by its arithmetic with the int16 tanh and one shift per hidden
layer. The integer precisions use no libm function (their exp and tanh are IEEE operations in a fixed order,
int8's tanh a table in integers), so their bits are the same on every machine; float32's tanhf is the C
library's, checked against the ONNX model by the export instead."""


def test_the_deployable_policy_has_no_host_code_and_fixed_width_types() -> None:
    files = generate(to_ir(tiny_model()))
    policy, host = files["policy.c"], files["policy_host.c"]
    for host_only in ("step_batch", "target_clones", "POLICY_TARGETS"):
        assert host_only not in policy and host_only not in files["policy.h"]
        assert host_only in host
    batch = "int policy_step_batch(int n, const float *obs, float *act, int *status);"
    assert batch in files["policy_host.h"]
    assert '#include "policy.c"' in host and '#include "policy_host.h"' in host
    assert re.findall(r"for \((\w+) ", policy) and set(re.findall(r"for \((\w+) ", policy)) == {"uint32_t"}
    assert "memcpy" not in policy  # the finite test reads the float's bits through a union (MISRA 21.15)
    header = files["policy.h"]
    _assert_fixed_width(header, policy)
    assert "#define POLICY_OBS_DIM 3u" in header and "#define POLICY_OK ((int32_t)0)" in header
    assert "int32_t policy_step(const float obs[POLICY_OBS_DIM], float act[POLICY_ACT_DIM]);" in header


def _assert_fixed_width(*sources: str) -> None:
    """No basic integer type in the code (MISRA C:2012 directive 4.6): sizes, indices, return codes and
    counters are fixed-width (comments aside)."""
    for source in sources:
        code = re.sub(r"/\*.*?\*/", "", source, flags=re.DOTALL)
        assert re.findall(r"\b(?:int|short|long|unsigned|signed)\b", code) == []


@pytest.fixture(scope="module")
@marks_its_users("slow")  # three exports (shared with the MISRA check's), three builds
def integer_exports(exported: Exported) -> dict[str, Path]:
    return {p: exported(SHIPPED_TD3, "--episodes", "0", "--quantize", p) for p in PINNED}


@pytest.mark.parametrize("precision", list(PINNED))
def test_the_integer_policies_give_the_pinned_bits_from_both_files(
    integer_exports: dict[str, Path], precision: str, tmp_path: Path
) -> None:
    export = integer_exports[precision]
    obs = _observations(export)
    _assert_fixed_width((export / "c" / "policy.h").read_text(), (export / "c" / "policy.c").read_text())
    build.make("lib", export / "c", tmp_path / "host")
    host = build.CPolicy(tmp_path / "host" / "libpolicy.so", "policy", obs.shape[1], 2)
    batch, codes = host.batch(obs)
    assert hashlib.sha256(batch.tobytes() + codes.tobytes()).hexdigest() == PINNED[precision]
    assert codes.tolist()[-4:-1] == [1, 1, 1]  # NaN, +inf and -inf observations: the safe action
    alone, alone_codes = _deployable_rows(export / "c", obs, tmp_path / "deployable.so")
    assert alone.view(np.uint32).tolist() == batch.view(np.uint32).tolist()
    assert alone_codes.tolist() == codes.tolist()


@pytest.fixture(scope="module")
@marks_its_users("slow")  # two exports (shared with other modules'), four builds
def step_exports(exported: Exported) -> dict[str, Path]:
    return {p: exported(SHIPPED_TD3, "--episodes", "0", *FLAGS[p]) for p in FLAGS}


FLAGS = {"float32": (), "int8": ("--quantize", "int8")}


@pytest.mark.parametrize("precision", list(FLAGS))
def test_the_hosts_step_is_the_avx2_clone_with_the_baseline_bits(
    step_exports: dict[str, Path], precision: str, tmp_path: Path
) -> None:
    export = step_exports[precision]
    obs = _observations(export)
    build.make("lib", export / "c", tmp_path / "clones")
    library = tmp_path / "clones" / "libpolicy.so"
    symbols = _symbols(library)
    assert symbols["policy_step"][0] == "i"  # an ifunc: the loader picks a clone
    assert {"policy_step.avx2", "policy_step.default"} <= set(symbols)
    assert "policy_step_deployable" not in symbols  # inlined into each clone (flatten)
    lib = ctypes.CDLL(str(library))
    base = _address(lib.policy_reset) - symbols["policy_reset"][1]
    picked = _address(lib.policy_step) - base  # dlsym answers an ifunc with the clone its resolver picked
    if "avx2" in cpu_flags():
        assert picked == symbols["policy_step.avx2"][1]
    build.make("lib", export / "c", tmp_path / "baseline", "-O2 -DPOLICY_ONE_TARGET")
    baseline_library = tmp_path / "baseline" / "libpolicy.so"
    assert "policy_step.avx2" not in _symbols(baseline_library)
    cloned = build.CPolicy(library, "policy", obs.shape[1], 2).rows(obs)
    baseline = build.CPolicy(baseline_library, "policy", obs.shape[1], 2).rows(obs)
    assert cloned[0].view(np.uint32).tolist() == baseline[0].view(np.uint32).tolist()
    assert cloned[1].tolist() == baseline[1].tolist()
    if precision in PINNED:
        assert hashlib.sha256(cloned[0].tobytes() + cloned[1].tobytes()).hexdigest() == PINNED[precision]


def _symbols(library: Path) -> dict[str, tuple[str, int]]:
    """The library's symbols (binutils ``nm``): name -> (type letter, address)."""
    out = subprocess.run(["nm", str(library)], capture_output=True, text=True, check=True).stdout
    fields = (line.split() for line in out.splitlines())
    return {f[2]: (f[1], int(f[0], 16)) for f in fields if len(f) == 3}


def _address(function: Any) -> int:
    """Where a ctypes function of a loaded library starts."""
    address = ctypes.cast(function, ctypes.c_void_p).value
    assert address is not None
    return address


def _observations(export: Path) -> np.ndarray:
    """The verification's observations, then a NaN, a +inf, a -inf and a 1e30-scaled row."""
    obs = np.load(export / "test" / OBSERVATIONS_FILE)
    extra = np.array(obs[:4])
    extra[0, 0], extra[1, -1], extra[2, 1] = np.nan, np.inf, -np.inf
    extra[3] *= 1e30
    return np.ascontiguousarray(np.concatenate([obs, extra]), np.float32)


def _deployable_rows(c_dir: Path, obs: np.ndarray, library: Path) -> tuple[np.ndarray, np.ndarray]:
    """Each row through ``policy_step`` of ``policy.c`` compiled alone, as the firmware compiles it."""
    command = [*shlex.split(build.compiler()["command"]), "-fPIC", "-shared", "-o", str(library)]
    subprocess.run([*command, str(c_dir / "policy.c"), "-lm"], check=True, capture_output=True)
    lib = ctypes.CDLL(str(library))
    assert not hasattr(lib, "policy_step_batch")
    pointer = ctypes.POINTER(ctypes.c_float)
    lib.policy_step.argtypes, lib.policy_step.restype = [pointer, pointer], ctypes.c_int
    acts = np.zeros((len(obs), 2), np.float32)
    codes = np.zeros(len(obs), np.int32)
    for i, row in enumerate(obs):
        codes[i] = lib.policy_step(row.ctypes.data_as(pointer), acts[i].ctypes.data_as(pointer))
    return acts, codes
