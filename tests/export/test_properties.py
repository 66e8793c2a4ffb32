"""Property tests over random MLP shapes and activations, and exact float literals."""

from __future__ import annotations

import tempfile
from pathlib import Path

import numpy as np
import onnxruntime as ort
from hypothesis import given, settings
from hypothesis import strategies as st

from embedrl.export.ops.base import c_float
from tests.export.helpers import compile_model, mlp_model

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


def test_results_do_not_depend_on_the_optimisation_level(tmp_path: Path) -> None:
    # The study's 6-100-100-2 shape: the blocked, vectorised loops keep every output's summation order.
    rng = np.random.default_rng(5)
    model = mlp_model([6, 100, 100, 2], seed=5)
    x = rng.uniform(-2, 2, size=(2000, 6)).astype(np.float32)
    o0, _ = compile_model(model, tmp_path, opt="-O0").batch(x)
    o3, _ = compile_model(model, tmp_path, opt="-O3").batch(x)
    assert o0.tobytes() == o3.tobytes()
