"""Actions never leave the action space: interval bounds through the graph, and a clamp where needed."""

from __future__ import annotations

import json
from pathlib import Path

import numpy as np
import onnx
import onnxruntime as ort
from onnx import helper

from embedrl.cli import main
from embedrl.export.bounds import action_bounds, within
from embedrl.export.onnx_import import to_ir
from tests.export.helpers import make_model, mlp_model

OBS_LOW = np.array([-1.8, -0.15, -1, -1, -0.7, -2.0])
OBS_HIGH = np.array([1.8, 1.3, 1, 1, 0.7, 2.0])


def _unbounded(gain: float = 2.0) -> onnx.ModelProto:
    """A linear policy without tanh or clip: 2 * x[0] and -3 * x[1], far outside [-1, 1]."""
    w = np.zeros((2, 6), np.float32)
    w[0, 0], w[1, 1] = gain, -3.0
    node = helper.make_node("Gemm", ["x", "W"], ["y"], transB=1)
    return make_model([node], {"W": w}, 6, 2)


def test_bounds_contain_every_sampled_action_and_are_tight_for_tanh() -> None:
    model = mlp_model([6, 16, 16, 2], ["Relu", "Relu", "Identity"], seed=3)
    graph = to_ir(model)
    lo, hi = action_bounds(graph, OBS_LOW, OBS_HIGH)
    obs = np.random.default_rng(0).uniform(OBS_LOW, OBS_HIGH, (5000, 6)).astype(np.float32)
    actions = ort.InferenceSession(model.SerializeToString()).run(None, {"x": obs})[0]
    assert np.all(actions >= lo - 1e-5) and np.all(actions <= hi + 1e-5)
    tanh = to_ir(mlp_model([6, 8, 2]))
    assert within(action_bounds(tanh, OBS_LOW, OBS_HIGH), np.full(2, -1.0), np.full(2, 1.0))
    lo, hi = action_bounds(to_ir(_unbounded()), OBS_LOW, OBS_HIGH)
    np.testing.assert_allclose([lo, hi], [[-3.6, -3.9], [3.6, 0.45]], rtol=1e-12)


def test_an_unbounded_policy_is_clamped_to_the_action_space(tmp_path: Path) -> None:
    source = tmp_path / "linear.onnx"
    onnx.save(_unbounded(), str(source))
    out = tmp_path / "export"
    assert main(["export", str(source), "--out", str(out), "--episodes", "0"]) == 0
    report = json.loads((out / "export_report.json").read_text())
    assert report["action_clamp"]["added"] is True
    assert report["ops"][-2:] == ["Max", "Min"]
    assert report["verification"]["c_vs_onnxruntime_max_abs_error"] <= 1e-5
    session = ort.InferenceSession(str(out / "policy.onnx"))  # the export carries the clamped graph
    obs = np.array([[1.5, 0.9, 0, 1, 0, 0], [-1.5, -0.1, 0, 1, 0, 0], [0.2, 0.1, 0, 1, 0, 0]], np.float32)
    np.testing.assert_allclose(
        session.run(None, {"x": obs})[0], [[1.0, -1.0], [-1.0, 0.3], [0.4, -0.3]], atol=1e-6
    )
    bounded = tmp_path / "bounded"
    assert main(["export", str(out / "policy.onnx"), "--out", str(bounded), "--episodes", "0"]) == 0
    again = json.loads((bounded / "export_report.json").read_text())
    assert again["action_clamp"]["added"] is False  # already inside: no second clamp
