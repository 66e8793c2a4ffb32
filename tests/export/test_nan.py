"""NaN is a fault at every layer: every generated op keeps ONNX's NaN semantics, the export's NaN-propagation
check fails a generator that hides one, and a policy that is NaN only where sampling never looks gives the
safe action with a non-OK status, with and without the clamp the export appends."""

from __future__ import annotations

import json
from pathlib import Path

import numpy as np
import onnx
import onnxruntime as ort
import pytest
from onnx import helper

from embedrl.cli import main
from embedrl.export import build, fixed_point, full_integer, nan_check, regenerate
from embedrl.export.codegen import generate
from embedrl.export.errors import VerificationError
from embedrl.export.onnx_import import to_ir
from embedrl.export.ops import EMITTERS
from tests.export.helpers import make_model, mlp_model
from tests.export.test_ops import CASES, N
from tests.export.test_recurrent import _cell_model

F = np.float32
mk = helper.make_node
OK, ACT_NOT_FINITE = 0, 2


@pytest.mark.parametrize("case", sorted(CASES))
@pytest.mark.parametrize("quantize", [None, "int8-weights"])
def test_every_op_keeps_onnx_nan_semantics(case: str, quantize: str | None) -> None:
    nodes, inits, out_dim = CASES[case]
    graph = to_ir(make_model(nodes, inits, N, out_dim))
    if quantize and any(not EMITTERS[n.op].quantizable for n in graph.nodes):
        pytest.skip("no int8-weights code for this op")
    result = nan_check.check(graph, quantize, 17)
    computing = [n for n in graph.nodes if not EMITTERS[n.op].alias]
    assert result["ops"] + len(result["skipped"]) == len(computing)
    probed = [n for n in computing if not any(n.name in s for s in result["skipped"])]
    assert result["positions"] == sum(graph.size(n.inputs[0]) for n in probed) > 0 or not probed


@pytest.mark.parametrize("kind", ["LSTM", "GRU"])
@pytest.mark.parametrize("quantize", [None, "int8-weights"])
def test_recurrent_cells_keep_nan_in_their_output_and_state(kind: str, quantize: str | None) -> None:
    # onnxruntime's cells return finite numbers for a NaN input; ONNX's reference and the C give NaN.
    result = nan_check.check(to_ir(_cell_model(kind)), quantize, 17)
    assert result["ops"] == 1 and result["positions"] > 0


@pytest.mark.parametrize(
    ("op", "attribute", "hiding"),
    [
        ("Relu", "expression", "{x} > 0.0f ? {x} : 0.0f"),
        ("Max", "select", "fmaxf({a}, {b})"),
        ("Min", "select", "fminf({a}, {b})"),
        ("Clip", None, None),
    ],
)
def test_the_check_fails_a_generator_that_hides_nan(
    op: str, attribute: str | None, hiding: str | None, monkeypatch: pytest.MonkeyPatch
) -> None:
    case = {"Relu": "Relu", "Max": "Max", "Min": "Min", "Clip": "Clip both"}[op]
    nodes, inits, out_dim = CASES[case]
    graph = to_ir(make_model(nodes, inits, N, out_dim))
    if attribute is None:  # Clip written with fminf/fmaxf, as a hand-written runtime might
        monkeypatch.setattr(
            type(EMITTERS[op]),
            "emit",
            lambda self, node, ctx, n: [
                f"for (int i = 0; i < {n}; ++i) {{",
                f"    {ctx.ref(node.outputs[0])}[i] = "
                f"fminf(fmaxf({ctx.ref(node.inputs[0])}[i], -0.5f), 0.75f);",
                "}",
            ],
        )
    else:
        monkeypatch.setattr(type(EMITTERS[op]), attribute, hiding)
    with pytest.raises(VerificationError, match=f"NaN propagation: {op} node"):
        nan_check.check(graph, None, 17)


def _div_by_itself_model() -> onnx.ModelProto:
    """obs -> [x0 / x0, x] stacked as Max(x, x / x): NaN at x0 = 0 only in the second operand of Max."""
    nodes = [mk("Div", ["x", "x"], ["ratio"]), mk("Max", ["x", "ratio"], ["y"])]
    return make_model(nodes, {}, N, N)


def test_a_nan_in_a_second_runtime_operand_reaches_the_status(tmp_path: Path) -> None:
    graph = to_ir(_div_by_itself_model())
    policy = _compiled(generate(graph), tmp_path, N, N)
    x = np.linspace(0.1, 1, N).astype(F)
    x[0] = 0.0  # 0 / 0: NaN in Max's second operand, Max's first is 0 (fmaxf would return 0)
    action = policy(x)
    assert policy.status == ACT_NOT_FINITE and np.all(action == 0.0)
    x[0] = 0.5
    policy(x)
    assert policy.status == OK


def test_a_q15_section_refuses_a_nan_before_converting_it(tmp_path: Path) -> None:
    graph = to_ir(mlp_model([N, 8, 2]))
    samples = np.random.default_rng(0).uniform(-1, 1, size=(500, N)).astype(F)
    section = fixed_point.plan(graph, samples)
    # Without the step's own observation check, the NaN reaches the section's float-to-integer conversion.
    files = generate(graph, quantize="q15", section=section, checks=False)
    policy = _compiled(files, tmp_path, N, 2)
    x = samples[0].copy()
    policy(x)
    assert policy.status == OK
    x[3] = np.nan
    action = policy(x)
    assert policy.status == ACT_NOT_FINITE and np.all(action == 0.0)


def _compiled(files: dict[str, str], tmp: Path, obs_dim: int, act_dim: int) -> build.CPolicy:
    c_dir = tmp / "c"
    c_dir.mkdir()
    for filename, text in files.items():
        (c_dir / filename).write_text(text)
    build.make("lib", c_dir, tmp / "build")
    return build.CPolicy(tmp / "build" / "libpolicy.so", "policy", obs_dim, act_dim)


def _nan_at_zero_unclamped() -> onnx.ModelProto:
    """Actions W (x / x) + b: NaN only where an observation is exactly 0 (what CAN decodes for a tiny value),
    unbounded for the export, which appends a clamp to the action space."""
    rng = np.random.default_rng(3)
    inits = {"W": rng.normal(size=(2, 6)).astype(F), "b": np.array([-5.0, 0.2], F)}
    nodes = [mk("Div", ["x", "x"], ["ratio"]), mk("Gemm", ["ratio", "W", "b"], ["y"], transB=1)]
    return make_model(nodes, inits, 6, 2)


def _nan_in_a_hidden_layer() -> onnx.ModelProto:
    """A hidden unit h0 = x0 divided by itself, then Relu (which hid the NaN), a layer and tanh (no clamp)."""
    rng = np.random.default_rng(4)
    w1 = rng.normal(size=(8, 6)).astype(F)
    w1[0] = 0.0
    w1[0, 0] = 1.0
    b1 = rng.normal(scale=0.1, size=8).astype(F)
    b1[0] = 0.0
    inits = {"W1": w1, "b1": b1, "W2": rng.normal(size=(2, 8)).astype(F), "b2": np.zeros(2, F)}
    nodes = [
        mk("Gemm", ["x", "W1", "b1"], ["h"], transB=1),
        mk("Div", ["h", "h"], ["n"]),
        mk("Relu", ["n"], ["r"]),
        mk("Gemm", ["r", "W2", "b2"], ["g"], transB=1),
        mk("Tanh", ["g"], ["y"]),
    ]
    return make_model(nodes, inits, 6, 2)


@pytest.mark.parametrize(
    ("model", "clamped"), [(_nan_at_zero_unclamped, True), (_nan_in_a_hidden_layer, False)]
)
@pytest.mark.parametrize("quantize", [None, "int8-weights"])
def test_a_policy_nan_where_sampling_never_looks_gives_the_safe_action(
    model: object, clamped: bool, quantize: str | None, tmp_path: Path
) -> None:
    proto = model()  # type: ignore[operator]
    path = tmp_path / "in dir" / "nan.onnx"
    path.parent.mkdir()
    onnx.save(proto, path)
    out = tmp_path / "out dir"
    argv = ["export", str(path), "--out", str(out), "--obs-range=-10:10", "--act-range=-1:1"]
    argv += ["--sample-time", "0.1", "--safe-action", "0.25,0", "--episodes", "0"]
    assert main([*argv, *(["--quantize", quantize] if quantize else [])]) == 0
    report = json.loads((out / "export_report.json").read_text())
    assert report["action_clamp"]["added"] is clamped
    assert report["verification"]["nan_propagation"]["ops"] >= 2
    assert regenerate.mismatch(out) is None  # the report may build this C: it is the generator's
    policy = build.CPolicy(out / "bin" / "host" / "libpolicy.so", "policy", 6, 2)
    x = np.array([0.0, 1.0, -2.0, 3.0, 0.5, -0.5], F)
    session = ort.InferenceSession(str(out / "policy.onnx"), providers=["CPUExecutionProvider"])
    assert np.all(np.isnan(session.run(None, {"x": x.reshape(1, 6)})[0]))
    action = policy(x)
    assert policy.status == ACT_NOT_FINITE
    assert action.tolist() == [0.25, 0.0]
    x[0] = 2.0**-19  # just away from zero: an ordinary action
    assert np.all(np.abs(policy(x)) <= 1.0) and policy.status == OK


def test_an_int8_full_section_refuses_a_nan_before_converting_it(tmp_path: Path) -> None:
    graph = to_ir(mlp_model([N, 8, 2]))
    samples = np.random.default_rng(0).uniform(-1, 1, size=(500, N)).astype(F)
    section = full_integer.plan(graph, samples)
    files = generate(graph, quantize="int8", section=section, checks=False)
    policy = _compiled(files, tmp_path, N, 2)
    x = samples[0].copy()
    policy(x)
    assert policy.status == OK
    x[3] = np.inf
    action = policy(x)
    assert policy.status == ACT_NOT_FINITE and np.all(action == 0.0)
