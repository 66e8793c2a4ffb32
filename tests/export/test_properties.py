"""Property tests over random MLP shapes and activations, and exact float literals."""

from __future__ import annotations

import itertools
import tempfile
from pathlib import Path

import numpy as np
import onnxruntime as ort
from hypothesis import given, settings
from hypothesis import strategies as st
from onnx import helper

from export.codegen import c_float
from tests.export.helpers import compile_model, make_model

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
    nodes, inits, last = [], {}, "x"
    for i, (n_in, n_out) in enumerate(itertools.pairwise(widths)):
        inits[f"W{i}"] = rng.normal(scale=1 / np.sqrt(n_in), size=(n_out, n_in)).astype(np.float32)
        inits[f"b{i}"] = rng.normal(scale=0.1, size=n_out).astype(np.float32)
        nodes.append(helper.make_node("Gemm", [last, f"W{i}", f"b{i}"], [f"g{i}"], transB=1))
        out = "y" if i == len(acts) - 1 else f"a{i}"
        nodes.append(helper.make_node(acts[i], [f"g{i}"], [out]))
        last = out
    model = make_model(nodes, inits, widths[0], widths[-1])
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
    widths = [6, 100, 100, 2]
    nodes, inits, last = [], {}, "x"
    for i, (n_in, n_out) in enumerate(itertools.pairwise(widths)):
        inits[f"W{i}"] = rng.normal(scale=1 / np.sqrt(n_in), size=(n_out, n_in)).astype(np.float32)
        inits[f"b{i}"] = rng.normal(scale=0.1, size=n_out).astype(np.float32)
        nodes.append(helper.make_node("Gemm", [last, f"W{i}", f"b{i}"], [f"g{i}"], transB=1))
        out = "y" if i == 2 else f"a{i}"
        nodes.append(helper.make_node("Tanh" if i == 2 else "Relu", [f"g{i}"], [out]))
        last = out
    model = make_model(nodes, inits, 6, 2)
    x = rng.uniform(-2, 2, size=(2000, 6)).astype(np.float32)
    o0, _ = compile_model(model, tmp_path, opt="-O0").batch(x)
    o3, _ = compile_model(model, tmp_path, opt="-O3").batch(x)
    assert o0.tobytes() == o3.tobytes()
