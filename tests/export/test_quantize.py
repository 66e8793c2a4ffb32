"""--quantize int8-weights, q15 and int8: the Python model of the arithmetic and the generated C agree bit for
bit."""

from __future__ import annotations

import json
import platform
import re
import subprocess
import tempfile
from pathlib import Path

import numpy as np
import onnx
import pytest
from hypothesis import given, reject, settings
from hypothesis import strategies as st
from onnx import helper

from embedrl.export import build, fixed_point, full_integer, interpret, quantize, verify
from embedrl.export.codegen import generate
from embedrl.export.errors import UnrepresentableRangeError, UnsupportedOpError
from embedrl.export.onnx_import import to_ir
from embedrl.export.ops import squash
from embedrl.export.ops.deterministic import exp_det, tanh_det
from embedrl.export.ops.linear import (
    INT8_MAX,
    INT8_MIN,
    SHIFT_RANGE,
    quantize_columns,
    quantize_multiplier,
    requantize,
    requantize16,
    requantize16_source,
    requantize_source,
)
from tests.export.helpers import make_model, mlp_model

ACTIVATIONS = ("Relu", "Tanh", "Sigmoid", "LeakyRelu", "Identity")


def _compile_int8_weights(model: onnx.ModelProto, tmp: Path) -> build.CPolicy:
    graph = to_ir(model)
    (tmp / "c").mkdir()
    for filename, text in generate(graph, quantize="int8-weights").items():
        (tmp / "c" / filename).write_text(text)
    build.make("lib", tmp / "c", tmp / "b")
    return build.CPolicy(
        tmp / "b" / "libpolicy.so", "policy", graph.size(graph.input), graph.size(graph.output)
    )


@settings(max_examples=20, deadline=None)
@given(
    st.lists(st.integers(1, 20), min_size=2, max_size=4).flatmap(
        lambda w: st.tuples(
            st.just(w),
            st.lists(st.sampled_from(ACTIVATIONS), min_size=len(w) - 1, max_size=len(w) - 1),
            st.integers(0, 2**31 - 1),
        )
    )
)
def test_generated_int8_weights_c_equals_the_python_model_bit_for_bit(
    spec: tuple[list[int], list[str], int],
) -> None:
    widths, acts, seed = spec
    model = mlp_model(widths, acts, seed)
    x = np.random.default_rng(seed).normal(scale=3.0, size=(200, widths[0])).astype(np.float32)
    with tempfile.TemporaryDirectory() as tmp:
        policy = _compile_int8_weights(model, Path(tmp))
        got, codes = policy.batch(x)
        assert got.tobytes() == policy.rows(x)[0].tobytes()  # the batched entry point, row by row
        assert got.tobytes() == policy.rows(x)[0].tobytes()  # the batched entry point, row by row
    assert not codes.any()
    assert verify.bitwise_mismatches(got, quantize.evaluate(to_ir(model), x)) == 0


def test_int8_weights_stay_close_to_float() -> None:
    import onnxruntime as ort

    model = mlp_model([6, 100, 100, 2], ["Relu", "Relu", "Tanh"], 3)
    x = np.random.default_rng(0).uniform(-2, 2, size=(500, 6)).astype(np.float32)
    float_out = ort.InferenceSession(model.SerializeToString()).run(None, {"x": x})[0]
    assert np.max(np.abs(quantize.evaluate(to_ir(model), x) - float_out)) < 0.05


def test_weights_are_symmetric_int8_per_output_channel() -> None:
    w = np.array([[1.0, -0.01], [-2.0, 0.005], [0.5, 0.0]], dtype=np.float32)  # [K=3][N=2]
    q, scale = quantize_columns(w)
    assert q.dtype == np.int8 and q.shape == w.shape
    np.testing.assert_allclose(scale, [2.0 / 127, 0.01 / 127], rtol=1e-6)
    assert q[1, 0] == -127 and q[0, 1] == -127  # each column's largest weight maps to +-127
    assert np.max(np.abs(q.astype(np.float32) * scale - w)) <= np.max(scale) / 2 + 1e-9


def test_deterministic_exp_and_tanh_are_accurate() -> None:
    x = np.linspace(-20, 20, 20001, dtype=np.float32)
    np.testing.assert_allclose(tanh_det(x), np.tanh(x.astype(np.float64)), rtol=0, atol=2e-6)
    small = np.linspace(-10, 10, 2001, dtype=np.float32)
    np.testing.assert_allclose(exp_det(small), np.exp(small.astype(np.float64)), rtol=2e-6)
    assert tanh_det(np.array([9.5, -30.0], np.float32)).tolist() == [1.0, -1.0]


def test_int8_weights_reject_ops_without_an_exact_model() -> None:
    model = make_model([helper.make_node("Softplus", ["x"], ["y"], name="sp")], {}, 6, 6)
    with pytest.raises(
        UnsupportedOpError, match="Softplus node 'sp' is not supported with --quantize int8-weights"
    ):
        generate(to_ir(model), quantize="int8-weights")


def test_quantised_closed_loop_rule_is_two_percentage_points() -> None:
    def loop(ref: float, q: float) -> dict[str, object]:
        return {"episodes": 200, "reference": {"success_rate": ref}, "c": {"success_rate": q}}

    assert verify.quantized_closed_loop_failure(loop(0.99, 0.97)) is None
    message = verify.quantized_closed_loop_failure(loop(0.99, 0.96))
    assert message is not None and "96.0%" in message and "99.0%" in message


def _compile_q15(
    model: onnx.ModelProto, calibration: np.ndarray, tmp: Path
) -> tuple[build.CPolicy, fixed_point.FixedSection]:
    graph = to_ir(model)
    section = fixed_point.plan(graph, calibration)
    (tmp / "c").mkdir()
    for filename, text in generate(graph, quantize="q15", section=section).items():
        (tmp / "c" / filename).write_text(text)
    build.make("lib", tmp / "c", tmp / "b")
    policy = build.CPolicy(
        tmp / "b" / "libpolicy.so", "policy", graph.size(graph.input), graph.size(graph.output)
    )
    return policy, section


@settings(max_examples=15, deadline=None)
@given(
    st.lists(st.integers(1, 24), min_size=2, max_size=5).flatmap(
        lambda w: st.tuples(
            st.just(w), st.sampled_from(["Tanh", "Identity", "Sigmoid"]), st.integers(0, 2**31 - 1)
        )
    )
)
def test_generated_q15_c_equals_the_integer_model_bit_for_bit(spec: tuple[list[int], str, int]) -> None:
    widths, last, seed = spec
    acts = ["Relu"] * (len(widths) - 2) + [last]
    model = mlp_model(widths, acts, seed)
    rng = np.random.default_rng(seed)
    calibration = rng.normal(scale=2.0, size=(300, widths[0])).astype(np.float32)
    x = rng.normal(scale=3.0, size=(300, widths[0])).astype(np.float32)  # wider than calibrated: saturation
    with tempfile.TemporaryDirectory() as tmp:
        policy, section = _compile_q15(model, calibration, Path(tmp))
        got, codes = policy.batch(x)
        assert got.tobytes() == policy.rows(x)[0].tobytes()  # the batched entry point, row by row
    assert not codes.any()
    assert verify.bitwise_mismatches(got, quantize.evaluate(to_ir(model), x, section)) == 0


def test_q15_is_close_to_float_within_the_calibrated_range() -> None:
    import onnxruntime as ort

    model = mlp_model([6, 100, 100, 2], ["Relu", "Relu", "Tanh"], 3)
    x = np.random.default_rng(0).uniform(-2, 2, size=(500, 6)).astype(np.float32)
    section = fixed_point.plan(to_ir(model), x)
    float_out = ort.InferenceSession(model.SerializeToString()).run(None, {"x": x})[0]
    assert np.max(np.abs(quantize.evaluate(to_ir(model), x, section) - float_out)) < 0.01


def test_q15_rejects_layers_joined_by_anything_but_relu() -> None:
    model = mlp_model([4, 8, 2], ["Sigmoid", "Tanh"], 0)
    with pytest.raises(UnsupportedOpError, match=r"Sigmoid node .* between layers is not supported with q15"):
        fixed_point.plan(to_ir(model), np.zeros((4, 4), np.float32))


def _compile_int8_full(
    model: onnx.ModelProto, calibration: np.ndarray, tmp: Path
) -> tuple[build.CPolicy, full_integer.IntegerSection]:
    graph = to_ir(model)
    section = full_integer.plan(graph, calibration)
    (tmp / "c").mkdir()
    for filename, text in generate(graph, quantize="int8", section=section).items():
        (tmp / "c" / filename).write_text(text)
    build.make("lib", tmp / "c", tmp / "b")
    policy = build.CPolicy(
        tmp / "b" / "libpolicy.so", "policy", graph.size(graph.input), graph.size(graph.output)
    )
    return policy, section


def _gemmlowp(acc: int, m: int, shift: int) -> int:
    """gemmlowp's MultiplyByQuantizedMultiplier in Python integers, as TFLite writes it."""
    left, right = max(shift, 0), max(-shift, 0)
    x = max(-(2**31), min(2**31 - 1, acc * 2**left))
    ab = x * m
    nudge = 2**30 if ab >= 0 else 1 - 2**30
    high = abs(ab + nudge) // 2**31 * (1 if ab + nudge >= 0 else -1)  # C's division truncates
    mask = 2**right - 1
    threshold = (mask >> 1) + (1 if high < 0 else 0)
    return int((high >> right) + (1 if (high & mask) > threshold else 0))


def test_requantisation_rounds_as_gemmlowp() -> None:
    rng = np.random.default_rng(0)
    acc = np.concatenate(
        [rng.integers(-(2**31), 2**31, 4000), [0, 1, -1, 2**31 - 1, -(2**31), 2**30, -(2**30)]]
    )
    m = rng.integers(2**30, 2**31, acc.size)
    shift = rng.integers(SHIFT_RANGE[0], SHIFT_RANGE[1] + 1, acc.size)
    shift[:1000] = rng.integers(-12, 1, 1000)  # the usual range: most outputs not rounded to 0 or saturated
    got = requantize(acc.astype(np.int64), m.astype(np.int64), shift.astype(np.int64))
    want = [_gemmlowp(int(a), int(b), int(s)) for a, b, s in zip(acc, m, shift, strict=True)]
    assert got.tolist() == want
    # Halves as gemmlowp rounds them (nudge 1 - 2^30 below 0): 1.5 -> 2, 0.5 -> 1, -1.5 -> -1, -0.5 -> 0
    assert quantize_multiplier(0.5) == (2**30, 0)
    halves = requantize(np.array([3, 1, -3, -1]), np.full(4, 2**30), np.zeros(4, np.int64))
    assert halves.tolist() == [2, 1, -1, 0]
    assert quantize_multiplier(2.0**-33) is None and quantize_multiplier(2.0**31) is None
    assert quantize_multiplier(0.0) is None and quantize_multiplier(float("nan")) is None


REQUANT_HARNESS = """#include <stdint.h>
#include <stdio.h>
%s
int main(void)
{
    long acc, m, shift, zero, low;
    while (scanf("%%ld %%ld %%ld %%ld %%ld", &acc, &m, &shift, &zero, &low) == 5) {
        const int8_t q = t_requantize((int32_t)acc, (int32_t)m, (int32_t)shift, (int32_t)zero, (int32_t)low);
        printf("%%d\\n", (int)q);
    }
    return 0;
}
"""


@pytest.mark.parametrize("level", ["-O0", "-O2"])
def test_generated_requantisation_equals_the_model_at_the_extremes(level: str, tmp_path: Path) -> None:
    """The C requantisation (one 64-bit sum for shift < 0, gemmlowp's steps otherwise), zero point and
    clamp against the model on random and extreme sums, multipliers and shifts."""
    rng = np.random.default_rng(1)
    edges = [-(2**31), -(2**31) + 1, -(2**30) - 1, -(2**30), -1, 0, 1, 2**30, 2**31 - 1]
    acc = np.concatenate([rng.integers(-(2**31), 2**31, 6000), np.repeat(edges, 8)])
    m = rng.integers(2**30, 2**31, acc.size)
    m[-len(edges) * 8 :: 2] = 2**31 - 1
    m[-len(edges) * 8 + 1 :: 2] = 2**30
    shift = rng.integers(SHIFT_RANGE[0], SHIFT_RANGE[1] + 1, acc.size)
    shift[:3000] = rng.integers(-12, 1, 3000)  # the usual range
    shift[-len(edges) * 8 :: 4] = SHIFT_RANGE[0]
    shift[-len(edges) * 8 + 2 :: 4] = -1
    zero = rng.integers(INT8_MIN, INT8_MAX + 1, acc.size)
    relu = rng.random(acc.size) < 0.5
    low = np.where(relu, zero, INT8_MIN)
    want = np.clip(requantize(acc, m, shift) + zero, low, INT8_MAX)
    (tmp_path / "r.c").write_text(REQUANT_HARNESS % requantize_source("t"))
    exe = tmp_path / "r"
    flags = ["-std=c99", "-Wall", "-Wextra", "-Werror", level]
    subprocess.run(["cc", *flags, "-o", str(exe), str(tmp_path / "r.c")], check=True)
    rows = "\n".join(" ".join(map(str, row)) for row in zip(acc, m, shift, zero, low, strict=True))
    got = subprocess.run([str(exe)], input=rows, capture_output=True, text=True, check=True).stdout.split()
    assert [int(v) for v in got] == want.tolist()


SQUASH_HARNESS = """#include <stdint.h>
#include <stdio.h>
%s

%s
int main(void)
{
    long acc, m, shift;
    while (scanf("%%ld %%ld %%ld", &acc, &m, &shift) == 3) {
        const int32_t t = t_requantize16((int32_t)acc, (int32_t)m, (int32_t)shift);
        printf("%%ld %%a %%a\\n", (long)t, (double)(%s), (double)(%s));
    }
    return 0;
}
"""


def test_int16_tanh_and_sigmoid_state_their_worst_error() -> None:
    """Over every int16 input the table's tanh is within :data:`TANH_WORST_ERROR` of tanh (and that is its
    worst, to 1e-5), sigmoid within half of it; both odd/symmetric and monotone."""
    t = np.arange(squash.INT16_MIN, squash.INT16_MAX + 1, dtype=np.int64)
    x = t / 2.0**squash.FRAC
    tanh_error = np.abs(squash.squash_model(t, "Tanh") - np.tanh(x))
    assert squash.TANH_WORST_ERROR - 1e-5 < tanh_error.max() <= squash.TANH_WORST_ERROR
    sigmoid = squash.squash_model(t, "Sigmoid").astype(np.float64)
    assert np.abs(sigmoid - 1 / (1 + np.exp(-2 * x))).max() <= squash.TANH_WORST_ERROR / 2
    r = squash.tanh_q15(t)
    assert np.all(np.diff(r) >= 0) and np.array_equal(r[1:], -r[1:][::-1])
    assert squash.TABLE.size * 2 == 66  # the flash it costs: 33 int16 entries


@pytest.mark.parametrize("level", ["-O0", "-O2"])
def test_generated_int16_tanh_and_sigmoid_equal_the_model_on_every_int16_input(
    level: str, tmp_path: Path
) -> None:
    """The C requantisation to int16 and tanh and sigmoid against the model: sums that land on every int16
    value (m = 2^30, shift 0: t = acc / 2 rounded), and random sums, multipliers and shifts (saturating)."""
    rng = np.random.default_rng(2)
    acc = np.concatenate(
        [np.arange(2 * squash.INT16_MIN - 3, 2 * squash.INT16_MAX + 4), rng.integers(-(2**31), 2**31, 3000)]
    )
    m = np.concatenate([np.full(acc.size - 3000, 2**30), rng.integers(2**30, 2**31, 3000)])
    shift = np.concatenate(
        [np.zeros(acc.size - 3000, np.int64), rng.integers(SHIFT_RANGE[0], SHIFT_RANGE[1] + 1, 3000)]
    )
    t = requantize16(acc, m, shift)
    (tmp_path / "s.c").write_text(
        SQUASH_HARNESS
        % (
            squash.tanh_source("t"),
            requantize16_source("t"),
            squash.squash_c("t", "Tanh", "t"),
            squash.squash_c("t", "Sigmoid", "t"),
        )
    )
    exe = tmp_path / "s"
    flags = ["-std=c99", "-Wall", "-Wextra", "-Werror", level]
    subprocess.run(["cc", *flags, "-o", str(exe), str(tmp_path / "s.c")], check=True)
    rows = "\n".join(f"{a} {b} {s}" for a, b, s in zip(acc, m, shift, strict=True))
    out = subprocess.run([str(exe)], input=rows, capture_output=True, text=True, check=True).stdout.split(
        "\n"
    )
    got = np.array([line.split() for line in out if line])
    assert got[:, 0].astype(np.int64).tolist() == t.tolist()
    tanh = np.array([float.fromhex(v) for v in got[:, 1]], np.float32)
    sigmoid = np.array([float.fromhex(v) for v in got[:, 2]], np.float32)
    assert tanh.tobytes() == squash.squash_model(t, "Tanh").tobytes()
    assert sigmoid.tobytes() == squash.squash_model(t, "Sigmoid").tobytes()
    assert len(set(t[: acc.size - 3000].tolist())) == 2**16  # every int16 input
    halves = requantize16(np.array([3, 1, -3, -1]), np.full(4, 2**30), np.zeros(4, np.int64))
    assert halves.tolist() == [2, 1, -1, 0]  # one rounding, half up: 1.5, 0.5, -1.5, -0.5


@settings(max_examples=15, deadline=None)
@given(
    st.lists(st.integers(1, 40), min_size=2, max_size=5).flatmap(
        lambda w: st.tuples(
            st.just(w), st.sampled_from(["Tanh", "Identity", "Sigmoid"]), st.integers(0, 2**31 - 1)
        )
    )
)
def test_generated_int8_full_c_equals_the_integer_model_bit_for_bit(spec: tuple[list[int], str, int]) -> None:
    widths, last, seed = spec
    acts = ["Relu"] * (len(widths) - 2) + [last]
    model = mlp_model(widths, acts, seed)
    rng = np.random.default_rng(seed)
    calibration = rng.normal(scale=2.0, size=(300, widths[0])).astype(np.float32)
    x = rng.normal(scale=3.0, size=(2000, widths[0])).astype(np.float32)  # wider than calibrated: saturation
    try:
        full_integer.plan(to_ir(model), calibration)
    except UnrepresentableRangeError as refusal:  # a dead ReLU layer's range, say: refused, naming the layer
        assert re.match(r"^int8: layer '.*' output \d+: ", str(refusal))
        reject()
    with tempfile.TemporaryDirectory() as tmp:
        policy, section = _compile_int8_full(model, calibration, Path(tmp))
        got, codes = policy.batch(x)
        assert got.tobytes() == policy.rows(x)[0].tobytes()  # the batched entry point, row by row
    assert not codes.any()
    assert verify.bitwise_mismatches(got, quantize.evaluate(to_ir(model), x, section)) == 0


def _normalised_mlp(seed: int) -> onnx.ModelProto:
    """An observation normalisation before a 5 -> 16 -> 3 chain: (x - mean) / std, clipped to [-3, 3], then
    times a per-feature factor with negative entries (a clamp before a decreasing map)."""
    rng = np.random.default_rng(seed)
    model = mlp_model([5, 16, 3], ["Relu", "Tanh"], seed)
    inits = {
        "mean": rng.normal(size=5).astype(np.float32),
        "std": rng.uniform(0.2, 3.0, size=5).astype(np.float32),
        "lo": np.float32(-3.0),
        "hi": np.float32(3.0),
        "k": np.array([1.5, -0.5, 1.0, -2.0, 0.75], np.float32),
    }
    nodes = [
        helper.make_node("Sub", ["x", "mean"], ["centred"], name="sub"),
        helper.make_node("Div", ["centred", "std"], ["scaled"], name="div"),
        helper.make_node("Clip", ["scaled", "lo", "hi"], ["clipped"], name="clip"),
        helper.make_node("Mul", ["clipped", "k"], ["normalised"], name="mul"),
    ]
    layers = list(model.graph.node)
    layers[0].input[0] = "normalised"
    weights = {i.name: onnx.numpy_helper.to_array(i) for i in model.graph.initializer}
    return make_model(nodes + layers, {**weights, **inits}, 5, 3)


def test_int8_full_folds_the_observation_normalisation_into_the_input_quantisation(tmp_path: Path) -> None:
    """Sub, Div, Clip and Mul before the chain become one multiply-add and clamp per feature: no float loop
    of theirs in the C, the C bit-exact with the integer model on 10,000 samples (a third beyond the clip),
    and within one int8 step of quantising the float normalisation's output."""
    model = _normalised_mlp(7)
    graph = to_ir(model)
    rng = np.random.default_rng(7)
    calibration = rng.normal(size=(300, 5)).astype(np.float32)
    x = (rng.normal(size=(10_000, 5)) * rng.choice([1.0, 10.0], size=(10_000, 1), p=[2 / 3, 1 / 3])).astype(
        np.float32
    )
    policy, section = _compile_int8_full(model, calibration, tmp_path)
    assert section.input == "x" and section.folded == ("sub", "div", "clip", "mul")
    text = (tmp_path / "c" / "policy.c").read_text()
    assert "Sub 'sub'" not in text and "Clip 'clip'" not in text and "folded in: sub, div, clip, mul" in text
    got, codes = policy.batch(x)
    assert not codes.any()
    assert verify.bitwise_mismatches(got, quantize.evaluate(graph, x, section)) == 0
    normalised = interpret.run(graph, x, "float64")["normalised"].astype(np.float32)
    unfolded = full_integer.quantize_input(normalised, section.quant)
    steps = np.abs(full_integer.map_input(x, section.input_map) - unfolded)
    assert steps.max() <= 1 and np.mean(steps > 0) < 0.01


def test_int8_full_keeps_float_ops_it_cannot_fold() -> None:
    """A factor of 0 maps a feature to a constant (no scale to fold): the ops stay float and the chain's input
    is quantised as it is."""
    model = _normalised_mlp(7)
    k = next(i for i in model.graph.initializer if i.name == "k")
    k.CopyFrom(onnx.numpy_helper.from_array(np.array([1.5, 0.0, 1.0, -2.0, 0.75], np.float32), "k"))
    section = full_integer.plan(to_ir(model), np.ones((4, 5), np.float32))
    assert section.input == "normalised" and section.folded == ()


HOST_BUILDS = ("-O0", "-O2", "-O3", "-O2 -DPOLICY_ONE_TARGET", "-O2 -DPOLICY_PORTABLE")
"""The host loop at every level, in its baseline (SSE2) build alone, and the portable loop on the host."""


@pytest.mark.parametrize("widths", [[7, 37, 19, 3], [6, 37, 18, 3]])
def test_int8_full_host_and_portable_loops_give_the_models_bits_at_every_level(
    tmp_path: Path, widths: list[int]
) -> None:
    """Outputs not a multiple of the host loop's rows, inputs not a multiple of its vectors, saturated
    inputs: every build gives the integer model's bits. Inputs beyond whole words: three (padded), one and
    two (tail words, with a block of one row)."""
    model = mlp_model(widths, ["Relu", "Relu", "Tanh"], 5)
    rng = np.random.default_rng(5)
    calibration = rng.normal(scale=2.0, size=(300, widths[0])).astype(np.float32)
    x = rng.normal(scale=3.0, size=(3000, widths[0])).astype(np.float32)
    graph = to_ir(model)
    section = full_integer.plan(graph, calibration)
    want = quantize.evaluate(graph, x, section)
    (tmp_path / "c").mkdir()
    for filename, text in generate(graph, quantize="int8", section=section).items():
        (tmp_path / "c" / filename).write_text(text)
    for k, opt in enumerate(HOST_BUILDS):
        build.make("lib", tmp_path / "c", tmp_path / f"b{k}", opt=opt)
        policy = build.CPolicy(tmp_path / f"b{k}" / "libpolicy.so", "policy", widths[0], widths[-1])
        assert verify.bitwise_mismatches(policy.rows(x)[0], want) == 0, opt


@pytest.mark.skipif(platform.machine() != "x86_64", reason="the host loop is x86-64's")
def test_int8_full_host_loop_multiplies_with_pmaddwd(tmp_path: Path) -> None:
    """The host build's step sums int16 pairs with pmaddwd (gcc's vectorised dot product, x86-64's baseline
    SSE2); the portable loop does not."""
    model = mlp_model([6, 100, 100, 2], ["Relu", "Relu", "Tanh"], 3)
    graph = to_ir(model)
    section = full_integer.plan(graph, np.random.default_rng(0).normal(size=(200, 6)).astype(np.float32))
    (tmp_path / "c").mkdir()
    for filename, text in generate(graph, quantize="int8", section=section).items():
        (tmp_path / "c" / filename).write_text(text)
    counts = {}
    for opt in ("-O2", "-O2 -DPOLICY_PORTABLE"):
        build.make("lib", tmp_path / "c", tmp_path / opt.replace(" ", ""), opt=opt)
        library = tmp_path / opt.replace(" ", "") / "libpolicy.so"
        text = subprocess.run(["objdump", "-d", str(library)], capture_output=True, text=True).stdout
        counts[opt] = text.count("pmaddwd")
    assert counts["-O2"] > 0 and counts["-O2 -DPOLICY_PORTABLE"] == 0


def test_int8_full_is_close_to_float_within_the_calibrated_range() -> None:
    import onnxruntime as ort

    model = mlp_model([6, 100, 100, 2], ["Relu", "Relu", "Tanh"], 3)
    x = np.random.default_rng(0).uniform(-2, 2, size=(2000, 6)).astype(np.float32)
    section = full_integer.plan(to_ir(model), x)
    float_out = ort.InferenceSession(model.SerializeToString()).run(None, {"x": x})[0]
    error = np.abs(quantize.evaluate(to_ir(model), x, section) - float_out)
    assert np.max(error) < 0.05 and np.mean(error) < 0.01
    hidden = section.layers[0]
    assert hidden.relu and hidden.out_zero == -128  # a ReLU output's range starts at 0: all 256 codes used


@pytest.mark.parametrize(
    ("bias", "why"),
    [
        (0.0, "requantisation scale .* cannot be represented"),
        (0.1, "its bias .* do not fit an int32 accumulator"),
    ],
)
def test_int8_full_refuses_a_scale_it_cannot_represent_naming_the_layer(bias: float, why: str) -> None:
    model = mlp_model([4, 8, 2], ["Relu", "Tanh"], 0)
    inits = {t.name: t for t in model.graph.initializer}
    w, b = (onnx.numpy_helper.to_array(inits[name]).copy() for name in ("W0", "b0"))
    w[3] *= np.float32(1e-20)  # output 3's weights 1e20 x smaller than the others' (Gemm, transB=1)
    b[3] = bias
    for name, array in (("W0", w), ("b0", b)):
        inits[name].CopyFrom(onnx.numpy_helper.from_array(array, name))
    graph = to_ir(model)
    calibration = np.random.default_rng(0).normal(size=(100, 4)).astype(np.float32)
    with pytest.raises(
        UnrepresentableRangeError, match=rf"^int8: layer '{graph.nodes[0].name}' output 3: {why}"
    ):
        full_integer.plan(graph, calibration)


def test_int8_full_rejects_layers_joined_by_anything_but_relu() -> None:
    model = mlp_model([4, 8, 2], ["Sigmoid", "Tanh"], 0)
    with pytest.raises(UnsupportedOpError, match=r"Sigmoid node .* not supported with int8"):
        full_integer.plan(to_ir(model), np.zeros((4, 4), np.float32))


def test_a_report_naming_int8_with_the_weight_only_schemes_description_is_refused(tmp_path: Path) -> None:
    """An export whose report says ``int8`` but describes the weight-only scheme (int8's meaning before it
    named the full-integer scheme) is refused in one line, not modelled with the wrong arithmetic."""
    from embedrl.export.errors import ExportError
    from embedrl.export.reference import REPORT_FILE, precision_of

    def report(scheme: str) -> Path:
        folder = tmp_path / scheme
        folder.mkdir()
        content = {"quantize": "int8", "verification": {"quantization": {"scheme": quantize.SCHEMES[scheme]}}}
        (folder / REPORT_FILE).write_text(json.dumps(content))
        return folder

    assert precision_of(report("int8")) == "int8"
    with pytest.raises(
        ExportError, match=r"its 'int8' is 'int8 weights per output channel.*export the policy again$"
    ):
        precision_of(report("int8-weights"))


def test_int8_full_stores_a_layers_biases_as_int16_where_every_one_fits(tmp_path: Path) -> None:
    """Biases in accumulator units (with the input's zero point folded in): int16 for a layer whose every
    bias fits, int32 for one with a bias beyond; the C still gives the model's bits."""
    model = mlp_model([6, 40, 40, 2], ["Relu", "Relu", "Tanh"], 3)
    big = next(i for i in model.graph.initializer if i.name == "b1")
    big.CopyFrom(onnx.numpy_helper.from_array(np.full(40, 3.0, np.float32), "b1"))
    rng = np.random.default_rng(3)
    calibration = rng.normal(size=(300, 6)).astype(np.float32)
    policy, section = _compile_int8_full(model, calibration, tmp_path)
    fits = [bool(np.all(np.abs(layer.bias) <= 2**15 - 1)) for layer in section.layers]
    assert fits == [True, False, False]
    text = (tmp_path / "c" / "policy.c").read_text()
    for layer, ctype in zip(section.layers, ("int16_t", "int32_t", "int32_t"), strict=True):
        assert re.search(
            rf"/\* \w+: {re.escape(layer.name)} bias in accumulator units \*/\nstatic const {ctype} ", text
        )
    x = rng.normal(scale=3.0, size=(2000, 6)).astype(np.float32)
    assert verify.bitwise_mismatches(policy.rows(x)[0], quantize.evaluate(to_ir(model), x, section)) == 0


def test_int8_full_layers_share_one_shift_where_every_multiplier_keeps_24_bits(tmp_path: Path) -> None:
    """A hidden layer's channels share the largest shift, each multiplier rescaled to it keeping at least 24
    significant bits (within 2^-24 of its scale): the shift is a constant of the C, no table. A spread of
    scales wider than 2^7 keeps a shift per channel."""
    real = np.array([0.003, 0.0011, 0.0052, 0.0007])
    pairs = [quantize_multiplier(float(r)) for r in real]
    m, shift = (np.array(v, np.int64) for v in zip(*pairs, strict=True))
    common_m, common = full_integer.common_shift(real, m, shift)
    assert len(set(shift.tolist())) > 1 and set(common.tolist()) == {int(shift.max())}
    assert np.all(common_m >= 2**23) and np.all(common_m < 2**31)
    assert np.max(np.abs(common_m * 2.0 ** (common - 31) - real) / real) <= 2.0**-24
    wide = np.array([0.003, 0.003 / 2**8])
    pairs = [quantize_multiplier(float(r)) for r in wide]
    m, shift = (np.array(v, np.int64) for v in zip(*pairs, strict=True))
    assert full_integer.common_shift(wide, m, shift)[1].tolist() == shift.tolist()
    model = mlp_model([6, 40, 40, 2], ["Relu", "Relu", "Tanh"], 3)
    calibration = np.random.default_rng(3).normal(size=(300, 6)).astype(np.float32)
    _, section = _compile_int8_full(model, calibration, tmp_path)
    text = (tmp_path / "c" / "policy.c").read_text()
    for layer in section.layers[:-1]:
        assert len(set(layer.shift.tolist())) == 1 and f"/* {layer.name} shifts */" not in text
