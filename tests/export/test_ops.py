"""Per-op tests: the generated C against onnxruntime and onnx.reference on the same inputs."""

from __future__ import annotations

import subprocess
import sys
from pathlib import Path
from typing import Any, cast

import numpy as np
import onnx
import onnxruntime as ort
import pytest
from onnx import helper
from onnx.reference import ReferenceEvaluator

from embedrl.export import interpret
from embedrl.export.bounds import action_bounds
from embedrl.export.onnx_import import to_ir
from embedrl.export.ops import EMITTERS
from embedrl.export.ops.elementwise import Relu
from embedrl.export.ops.linear import pack_passes
from tests.export.helpers import compile_model, make_model
from tests.export.test_recurrent import RECURRENT_OPS

F = np.float32
RNG = np.random.default_rng(0)
N = 7
W = RNG.normal(size=(5, N)).astype(F)  # [out, in]
B5 = RNG.normal(size=5).astype(F)
V = RNG.normal(size=N).astype(F)
POSITIVE = (RNG.random(N) + 0.5).astype(F)
mk = helper.make_node

# name: (nodes, initializers, output dim)
CASES: dict[str, tuple[list[onnx.NodeProto], dict[str, Any], int]] = {
    "Gemm transB=1 with bias": ([mk("Gemm", ["x", "W", "b"], ["y"], transB=1)], {"W": W, "b": B5}, 5),
    "Gemm transB=0 without bias": ([mk("Gemm", ["x", "WT"], ["y"])], {"WT": W.T.copy()}, 5),
    "Gemm alpha beta scalar C": (
        [mk("Gemm", ["x", "W", "c"], ["y"], transB=1, alpha=0.5, beta=-2.0)],
        {"W": W, "c": F(0.25)},
        5,
    ),
    "MatMul then Add": (
        [mk("MatMul", ["x", "WT"], ["m"]), mk("Add", ["m", "b"], ["y"])],
        {"WT": W.T.copy(), "b": B5},
        5,
    ),
    "Add vector": ([mk("Add", ["x", "v"], ["y"])], {"v": V}, N),
    "Add constant first": ([mk("Add", ["v", "x"], ["y"])], {"v": V}, N),
    "Sub scalar": ([mk("Sub", ["x", "s"], ["y"])], {"s": F(1.5)}, N),
    "Mul vector [1,N]": ([mk("Mul", ["x", "v"], ["y"])], {"v": V.reshape(1, N)}, N),
    "Div vector": ([mk("Div", ["x", "p"], ["y"])], {"p": POSITIVE}, N),
    "Add two runtime values": ([mk("Relu", ["x"], ["r"]), mk("Add", ["x", "r"], ["y"])], {}, N),
    "Max": ([mk("Max", ["x", "v"], ["y"])], {"v": V}, N),
    "Min": ([mk("Min", ["x", "v"], ["y"])], {"v": V}, N),
    "Relu": ([mk("Relu", ["x"], ["y"])], {}, N),
    "LeakyRelu": ([mk("LeakyRelu", ["x"], ["y"], alpha=0.2)], {}, N),
    "LeakyRelu default alpha": ([mk("LeakyRelu", ["x"], ["y"])], {}, N),
    "Tanh": ([mk("Tanh", ["x"], ["y"])], {}, N),
    "Sigmoid": ([mk("Sigmoid", ["x"], ["y"])], {}, N),
    "Softplus": ([mk("Softplus", ["x"], ["y"])], {}, N),
    "Clip both": ([mk("Clip", ["x", "lo", "hi"], ["y"])], {"lo": F(-0.5), "hi": F(0.75)}, N),
    "Clip min only": ([mk("Clip", ["x", "lo"], ["y"])], {"lo": F(-0.5)}, N),
    "Clip max only": ([mk("Clip", ["x", "", "hi"], ["y"])], {"hi": F(0.75)}, N),
    "Identity": ([mk("Identity", ["x"], ["y"])], {}, N),
    "Flatten": ([mk("Flatten", ["x"], ["y"], axis=1)], {}, N),
    "Reshape": (
        [mk("Reshape", ["x", "shape"], ["r"]), mk("Tanh", ["r"], ["y"])],
        {"shape": np.array([1, -1], dtype=np.int64)},
        N,
    ),
    "Unsqueeze then Squeeze": (
        [mk("Unsqueeze", ["x", "a1"], ["u"]), mk("Squeeze", ["u", "a1"], ["s"]), mk("Tanh", ["s"], ["y"])],
        {"a1": np.array([1], dtype=np.int64)},
        N,
    ),
    "Squeeze without axes": (
        [
            mk("Unsqueeze", ["x", "a0"], ["u"]),
            mk("Squeeze", ["u"], ["s"]),
            mk("Reshape", ["s", "shape"], ["y"]),
        ],
        {"a0": np.array([0], dtype=np.int64), "shape": np.array([1, -1], dtype=np.int64)},
        N,
    ),
    "Gather of a one-step sequence": (
        [
            mk("Unsqueeze", ["x", "a0"], ["u"]),
            mk("Gather", ["u", "i0"], ["g"], axis=0),
            mk("Relu", ["g"], ["y"]),
        ],
        {"a0": np.array([0], dtype=np.int64), "i0": np.array(0, dtype=np.int64)},
        N,
    ),
    "Constant operand": (
        [mk("Constant", [], ["c"], value=onnx.numpy_helper.from_array(V, "c")), mk("Mul", ["x", "c"], ["y"])],
        {},
        N,
    ),
}


def _inputs() -> np.ndarray:
    x = RNG.normal(scale=3.0, size=(200, N)).astype(F)
    x[0] = 0.0
    x[1, :] = 40.0  # large values: Softplus and Sigmoid away from zero
    x[2, :] = -40.0
    return x


@pytest.mark.parametrize("case", sorted(CASES))
def test_op_matches_onnxruntime_and_reference(case: str, tmp_path: Path) -> None:
    nodes, inits, out_dim = CASES[case]
    model = make_model(nodes, inits, N, out_dim)
    onnx.checker.check_model(model, full_check=True)
    policy = compile_model(model, tmp_path)
    session = ort.InferenceSession(model.SerializeToString(), providers=["CPUExecutionProvider"])
    reference = cast(Any, ReferenceEvaluator(model))
    for x in _inputs():
        row = x.reshape(1, N)
        expected_ort = session.run(None, {"x": row})[0].reshape(-1)
        expected_ref = np.asarray(reference.run(None, {"x": row})[0]).reshape(-1)
        got = policy(x)
        assert policy.status == 0
        scale = max(1.0, float(np.max(np.abs(expected_ort))))
        np.testing.assert_allclose(got, expected_ort, rtol=0, atol=1e-5 * scale)
        np.testing.assert_allclose(got, expected_ref, rtol=0, atol=1e-5 * scale)


FAST_MATH = "-O3 -march=native -ffast-math"
"""Flags embedded users often set: the compiler may then assume that no NaN or infinity exists."""


def test_non_finite_observation_gives_the_safe_action(tmp_path: Path) -> None:
    nodes, inits, out_dim = CASES["Gemm transB=1 with bias"]
    policy = compile_model(make_model(nodes, inits, N, out_dim), tmp_path)
    for bad in (np.nan, -np.nan, np.inf, -np.inf):
        x = V.copy()
        x[3] = bad
        assert np.array_equal(policy(x), np.zeros(5, F))
        assert policy.status == 1


def test_non_finite_result_gives_the_safe_action(tmp_path: Path) -> None:
    # Dividing by a zero weight makes infinities: the C must not let them out.
    model = make_model([mk("Div", ["x", "z"], ["y"])], {"z": np.zeros(N, F)}, N, N)
    policy = compile_model(model, tmp_path)
    out = policy(np.ones(N, F))
    assert policy.status == 2
    assert np.array_equal(out, np.zeros(N, F))
    out = policy(np.zeros(N, F))  # 0 / 0: NaN
    assert policy.status == 2 and np.array_equal(out, np.zeros(N, F))


FAST_MATH_CHECK = """
import sys
from pathlib import Path
import numpy as np
from tests.export.helpers import compile_model, make_model
from tests.export.test_recurrent import RECURRENT_OPS
from tests.export.test_ops import CASES, FAST_MATH, N, V, F, mk
tmp = Path(sys.argv[1])
nodes, inits, out_dim = CASES["Gemm transB=1 with bias"]
policy = compile_model(make_model(nodes, inits, N, out_dim), tmp, opt=FAST_MATH)
for bad in (np.nan, -np.nan, np.inf, -np.inf):
    x = V.copy()
    x[3] = bad
    out = policy(x)
    assert np.array_equal(out, np.zeros(5, F)) and policy.status == 1, ("observation", bad, policy.status)
divide = make_model([mk("Div", ["x", "z"], ["y"])], {"z": np.zeros(N, F)}, N, N)
div = compile_model(divide, tmp, opt=FAST_MATH)
for x in (np.ones(N, F), np.zeros(N, F)):
    out = div(x)
    assert div.status == 2 and np.array_equal(out, np.zeros(N, F)), ("result", div.status)
print("ok")
"""


def test_the_non_finite_guard_holds_under_fast_math(tmp_path: Path) -> None:
    # In a process of its own: a library built with -ffast-math switches the loading process's FPU to
    # flush denormals to zero, which would change every later test in this one.
    repo = Path(__file__).resolve().parents[2]
    done = subprocess.run(
        [sys.executable, "-c", FAST_MATH_CHECK, str(tmp_path)], cwd=repo, capture_output=True, text=True
    )
    assert done.returncode == 0 and done.stdout.strip() == "ok", done.stdout + done.stderr


def test_every_registered_op_has_a_test_case() -> None:
    tested = {node.op_type for nodes, _, _ in CASES.values() for node in nodes} | set(RECURRENT_OPS)
    assert tested == set(EMITTERS), f"ops without a case: {sorted(set(EMITTERS) - tested)}"


@pytest.mark.parametrize("case", sorted(CASES))
def test_interval_bounds_hold_every_output_of_every_op(case: str) -> None:
    """Each op's own interval rule (monotone ends, matrix rows, or unbounded) contains what it computes."""
    nodes, inits, out_dim = CASES[case]
    graph = to_ir(make_model(nodes, inits, N, out_dim))
    low, high = np.full(N, -3.0), np.full(N, 2.0)
    lo, hi = action_bounds(graph, low, high)
    x = RNG.uniform(low, high, size=(500, N))
    x[:2] = low, high
    y = interpret.run(graph, x, "float64")[graph.output]
    assert np.all(y >= lo - 1e-9) and np.all(y <= hi + 1e-9)


def test_an_op_that_is_not_monotone_is_not_bounded_by_its_ends() -> None:
    class Square(Relu):  # x^2: the ends of [-1, 1] both give 1, yet 0 is inside
        monotone = False

    node = to_ir(make_model([mk("Relu", ["x"], ["y"])], {}, N, N)).nodes[0]
    lo, hi = Square().bounds(node, (np.full(N, -1.0), np.full(N, 1.0)), {}, N)
    assert np.all(lo == -np.inf) and np.all(hi == np.inf)


def test_the_vldm_form_stores_each_pass_of_weights_where_its_loop_reads_it() -> None:
    """The C of the VLDM form reads the pass from output ``n`` (8, 4, 2, then 1 outputs: 23 = 2 x 8 + 4 + 2 +
    1) from ``n * K`` on, input by input, that input's weights of the pass in output order."""
    k, n = 5, 23
    w = np.arange(k * n, dtype=np.float32).reshape(k, n)
    packed = pack_passes(w)
    assert packed.dtype == np.float32 and packed.shape == (k * n,)
    first = 0
    for rows, count in ((8, 2), (4, 1), (2, 1), (1, 1)):
        for _ in range(count):
            np.testing.assert_array_equal(
                packed[first * k : (first + rows) * k].reshape(k, rows), w[:, first : first + rows]
            )
            first += rows
    assert first == n
