"""Property tests over random MLP shapes and activations, and exact float literals."""

from __future__ import annotations

import platform
import re
import subprocess
import tempfile
from pathlib import Path

import numpy as np
import onnxruntime as ort
import pytest
from hypothesis import given, settings
from hypothesis import strategies as st

from embedrl.export.contract.literals import c_float
from tests.export.helpers import compile_model, cpu_flags, mlp_model

ACTIVATIONS = ("Relu", "Tanh", "Sigmoid", "Softplus", "LeakyRelu", "Identity")


@st.composite
def mlps(draw: st.DrawFn) -> tuple[list[int], list[str], int]:
    widths = draw(st.lists(st.integers(1, 24), min_size=2, max_size=5))
    acts = draw(st.lists(st.sampled_from(ACTIVATIONS), min_size=len(widths) - 1, max_size=len(widths) - 1))
    seed = draw(st.integers(0, 2**31 - 1))
    return widths, acts, seed


@settings(max_examples=25, deadline=None)
@given(mlps())
def test_random_mlps_match_onnxruntime(spec: tuple[list[int], list[str], int]) -> None:
    widths, acts, seed = spec
    rng = np.random.default_rng(seed)
    model = mlp_model(widths, acts, seed)
    with tempfile.TemporaryDirectory() as tmp:
        policy = compile_model(model, Path(tmp))
        session = ort.InferenceSession(model.SerializeToString(), providers=["CPUExecutionProvider"])
        x = rng.normal(scale=2.0, size=(64, widths[0])).astype(np.float32)
        expected = session.run(None, {"x": x})[0]
        got, codes = policy.batch(x)
    assert not codes.any()
    np.testing.assert_allclose(got, expected, rtol=0, atol=1e-5)


@given(st.integers(0, 2**32 - 1))
def test_float_literals_round_trip_exactly(bits: int) -> None:
    value = np.array([bits], dtype=np.uint32).view(np.float32)[0]
    if not np.isfinite(value):
        return
    text = c_float(float(value))
    assert text.endswith("f") and any(c in text for c in ".e")
    assert np.float32(float(text[:-1])).tobytes() == value.tobytes()


def test_results_do_not_depend_on_the_optimisation_level_or_the_instruction_set(tmp_path: Path) -> None:
    """The study's 6-100-100-2 shape and odd widths: the blocked, vectorised loops keep every output's
    summation order at -O0 and -O3, in each target clone the default build picks from (compiled alone
    here, on the instruction sets this CPU runs) and in the batched entry point."""
    rng = np.random.default_rng(5)
    builds = ["-O0", "-O2", "-O3", "-O2 -DPOLICY_ONE_TARGET"]
    builds += ["-O2 -DPOLICY_ONE_TARGET -mavx2"] if "avx2" in cpu_flags() else []
    for widths in ([6, 100, 100, 2], [5, 37, 17, 3]):
        model = mlp_model(widths, seed=5)
        x = rng.uniform(-2, 2, size=(2000, widths[0])).astype(np.float32)
        reference, _ = compile_model(model, tmp_path, opt="-O0").rows(x)
        for opt in builds:
            policy = compile_model(model, tmp_path, opt=opt)
            assert policy.rows(x)[0].tobytes() == reference.tobytes(), opt
            assert policy.batch(x)[0].tobytes() == reference.tobytes(), f"{opt}, batched"


@pytest.mark.skipif(platform.machine() != "x86_64", reason="the target clones are x86-64's")
def test_the_default_build_has_an_avx2_clone_and_no_fused_multiply_add(tmp_path: Path) -> None:
    """The clones' bits agree because none can fuse a multiply and an add (AVX-512 would bring FMA). The host
    file's step (the deployable step inlined) and its block are cloned."""
    compile_model(mlp_model([6, 100, 100, 2], seed=1), tmp_path)
    library = next(tmp_path.glob("m*/build/libpolicy.so"))
    listing = subprocess.run(
        ["objdump", "-d", str(library)], capture_output=True, text=True, check=True
    ).stdout
    assert "<policy_block.avx2>:" in listing and "<policy_step.avx2>:" in listing
    assert re.search(r"\bvfn?m(add|sub)", listing) is None


def test_the_batched_entry_point_answers_each_row_as_the_step_does(tmp_path: Path) -> None:
    """Blocks of 8 rows and a partial last one; a row with NaN gets the safe action and its code, the rows
    around it are untouched; no rows, no work."""
    model = mlp_model([6, 100, 100, 2], seed=3)
    policy = compile_model(model, tmp_path)
    x = np.random.default_rng(3).uniform(-2, 2, size=(13, 6)).astype(np.float32)
    x[9, 2] = np.nan
    acts, codes = policy.batch(x)
    row_acts, row_codes = policy.rows(x)
    assert acts.tobytes() == row_acts.tobytes() and codes.tolist() == row_codes.tolist()
    assert codes.tolist() == [0] * 9 + [1] + [0] * 3
    np.testing.assert_array_equal(acts[9], np.zeros(2, np.float32))
    assert policy.batch(x[:0])[0].shape == (0, 2)
