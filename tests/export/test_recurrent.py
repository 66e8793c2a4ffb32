"""Recurrent policies: LSTM and GRU cells through the importer and the generated C, over sequences.

PyTorch's ``nn.LSTM``/``nn.GRU`` exported to ONNX (state as explicit inputs and outputs), and cells built by
hand with every GRU variant: the C against onnxruntime over whole sequences with the state carried and reset,
bit for bit the cell's float32 model, the same bits at -O0 and -O3.
"""

from __future__ import annotations

import warnings
from pathlib import Path
from typing import Any

import numpy as np
import onnx
import onnxruntime as ort
import pytest
import torch
from onnx import TensorProto, helper, numpy_helper

from embedrl.export import build, interpret, quantize
from embedrl.export.bounds import action_bounds
from embedrl.export.codegen import generate
from embedrl.export.errors import ExportError, UnsupportedOpError
from embedrl.export.onnx_import import to_ir
from embedrl.export.ops import EMITTERS
from embedrl.export.ops.recurrent import Recurrent
from embedrl.export.quantize import check_supported
from tests.export.helpers import compile_model

F = np.float32
OBS, HIDDEN, ACT, STEPS = 5, 16, 2, 200
RECURRENT_OPS = ("LSTM", "GRU")
"""The registered ops these tests cover (the per-op table of test_ops has the one-input ops)."""


class _Torch(torch.nn.Module):
    """obs [1, OBS] and the state -> tanh(linear(h)) and the next state, as users write a recurrent actor."""

    def __init__(self, kind: str) -> None:
        super().__init__()
        self.kind = kind
        self.cell = (torch.nn.LSTM if kind == "LSTM" else torch.nn.GRU)(OBS, HIDDEN)
        self.head = torch.nn.Linear(HIDDEN, ACT)

    def forward(self, obs: torch.Tensor, *state: torch.Tensor) -> tuple[torch.Tensor, ...]:
        x = obs.unsqueeze(0)  # one step of a sequence
        if self.kind == "LSTM":
            y, (h, c) = self.cell(x, (state[0], state[1]))
            return torch.tanh(self.head(y[0])), h, c
        y, h = self.cell(x, state[0])
        return torch.tanh(self.head(y[0])), h


def _state_names(kind: str) -> tuple[list[str], list[str]]:
    extra = ["c"] if kind == "LSTM" else []
    return ["obs", "h", *extra], ["act", "h_next", *(f"{e}_next" for e in extra)]


def torch_recurrent_onnx(kind: str, path: Path, seed: int = 0) -> Path:
    """``nn.LSTM`` or ``nn.GRU`` with a linear head, exported by torch.onnx (batch 1, one step per call)."""
    torch.manual_seed(seed)
    net = _Torch(kind).eval()
    inputs, outputs = _state_names(kind)
    args = (torch.zeros(1, OBS), *(torch.zeros(1, 1, HIDDEN) for _ in inputs[1:]))
    with warnings.catch_warnings():
        warnings.simplefilter("ignore")  # the TorchScript exporter's deprecation and RNN batch notes
        torch.onnx.export(
            net, args, str(path), input_names=inputs, output_names=outputs, dynamo=False, opset_version=17
        )
    return path


def _observations(seed: int = 1) -> np.ndarray:
    return np.random.default_rng(seed).uniform(-2.0, 2.0, (STEPS, OBS)).astype(F)


def _ort_sequence(model: onnx.ModelProto | Path, obs: np.ndarray) -> np.ndarray:
    """onnxruntime over the sequence, each step's next state fed to the next step, from zero state."""
    source = str(model) if isinstance(model, Path) else model.SerializeToString()
    session = ort.InferenceSession(source, providers=["CPUExecutionProvider"])
    names = [i.name for i in session.get_inputs()]
    state = {i.name: np.zeros(i.shape, F) for i in session.get_inputs()[1:]}
    actions = []
    for row in obs:
        out = session.run(None, {names[0]: row[None], **state})
        actions.append(np.asarray(out[0]).reshape(-1))
        state = dict(zip(state, out[1:], strict=True))
    return np.asarray(actions)


@pytest.mark.parametrize("kind", RECURRENT_OPS)
def test_a_torch_recurrent_policy_runs_in_c_as_in_onnxruntime_over_a_sequence(
    kind: str, tmp_path: Path
) -> None:
    path = torch_recurrent_onnx(kind, tmp_path / f"{kind}.onnx")
    graph = to_ir(onnx.load(str(path)))
    assert graph.state_size == HIDDEN * (2 if kind == "LSTM" else 1)
    obs = _observations()
    expected = _ort_sequence(path, obs)
    model = onnx.load(str(path))
    runs = {}
    for opt in ("-O0", "-O3"):
        policy = compile_model(model, tmp_path, opt=opt)
        policy.reset()
        runs[opt] = np.asarray([policy(row) for row in obs])
        assert policy.status == 0
        # a new episode: the same sequence from zero state gives the same actions again
        policy.reset()
        again = np.asarray([policy(row) for row in obs[:20]])
        assert np.array_equal(again, runs[opt][:20])
        # the batch of a recurrent policy is one sequence
        policy.reset()
        batch, codes = policy.batch(obs)
        assert np.array_equal(batch, runs[opt]) and not codes.any()
    np.testing.assert_allclose(runs["-O0"], expected, rtol=0, atol=1e-5)
    assert np.array_equal(runs["-O0"], runs["-O3"]), "-O0 and -O3 must give the same bits"
    np.testing.assert_allclose(interpret.run_sequence(graph, obs), expected, rtol=0, atol=1e-5)
    # memory matters: the same observation gives another action once the state has moved
    assert not np.allclose(runs["-O0"][0], _ort_sequence(path, obs[[5, 0]])[1], atol=1e-4)


def _cell_model(kind: str, linear_before_reset: int = 0, seed: int = 2) -> onnx.ModelProto:
    """obs -> one cell step -> action = the new hidden state; the state as graph inputs and outputs."""
    rng = np.random.default_rng(seed)
    gates = 4 if kind == "LSTM" else 3
    inits: dict[str, np.ndarray] = {
        "W": rng.normal(scale=0.6, size=(1, gates * HIDDEN, OBS)).astype(F),
        "R": rng.normal(scale=0.4, size=(1, gates * HIDDEN, HIDDEN)).astype(F),
        "B": rng.normal(scale=0.3, size=(1, 2 * gates * HIDDEN)).astype(F),
        "axes0": np.array([0], np.int64),
        "axes01": np.array([0, 1], np.int64),
    }
    state_in = ["h", "c"] if kind == "LSTM" else ["h"]
    attrs: dict[str, Any] = {"hidden_size": HIDDEN}
    if kind == "GRU":
        attrs["linear_before_reset"] = linear_before_reset
    nodes = [
        helper.make_node("Unsqueeze", ["obs", "axes0"], ["x"]),
        helper.make_node(
            kind, ["x", "W", "R", "B", "", *state_in], ["y", *(f"{s}_next" for s in state_in)], **attrs
        ),
        helper.make_node("Squeeze", ["y", "axes01"], ["act"]),
    ]
    graph = helper.make_graph(
        nodes,
        kind,
        [helper.make_tensor_value_info("obs", TensorProto.FLOAT, [1, OBS])]
        + [helper.make_tensor_value_info(s, TensorProto.FLOAT, [1, 1, HIDDEN]) for s in state_in],
        [helper.make_tensor_value_info("act", TensorProto.FLOAT, [1, HIDDEN])]
        + [helper.make_tensor_value_info(f"{s}_next", TensorProto.FLOAT, [1, 1, HIDDEN]) for s in state_in],
        [numpy_helper.from_array(v, k) for k, v in inits.items()],
    )
    return helper.make_model(graph, opset_imports=[helper.make_opsetid("", 17)], ir_version=8)


def _float32_model(model: onnx.ModelProto, obs: np.ndarray) -> np.ndarray:
    """The cell's float32 model (its reference in C precision) over the sequence: the action is h."""
    graph = to_ir(model)
    node = next(n for n in graph.nodes if n.op in RECURRENT_OPS)
    state = [np.zeros((1, HIDDEN), F) for _ in graph.states]
    weights = [graph.constants[i].reshape(-1) for i in node.inputs[1:4]]
    hs = []
    for row in obs:
        cell = EMITTERS[node.op]
        assert isinstance(cell, Recurrent)
        out = cell.float32_model(node, [row[None], *weights, *state], graph.constants)
        state = [out[1], out[2]] if node.op == "LSTM" else [out[1]]
        hs.append(out[0][0])
    return np.asarray(hs)


@pytest.mark.parametrize(("kind", "linear_before_reset"), [("LSTM", 0), ("GRU", 0), ("GRU", 1)])
def test_each_cell_is_bit_for_bit_its_float32_model_and_within_1e5_of_onnxruntime(
    kind: str, linear_before_reset: int, tmp_path: Path
) -> None:
    model = _cell_model(kind, linear_before_reset)
    onnx.checker.check_model(model, full_check=True)
    obs = _observations(seed=3)
    policy = compile_model(model, tmp_path, opt="-O2")
    got = np.asarray([policy(row) for row in obs])
    assert np.array_equal(got, _float32_model(model, obs))
    np.testing.assert_allclose(got, _ort_sequence(model, obs), rtol=0, atol=1e-5)
    graph = to_ir(model)
    lo, hi = action_bounds(graph, np.full(OBS, -2.0), np.full(OBS, 2.0))
    assert np.all(lo == -1.0) and np.all(hi == 1.0) and np.all(np.abs(got) <= 1.0)


def test_a_non_finite_observation_leaves_the_state_as_it_was(tmp_path: Path) -> None:
    model = _cell_model("LSTM")
    obs = _observations(seed=4)[:30]
    policy = compile_model(model, tmp_path)
    clean = np.asarray([policy(row) for row in obs])
    policy.reset()
    for k, row in enumerate(obs):
        if k == 10:
            bad = row.copy()
            bad[2] = np.nan
            assert np.array_equal(policy(bad), np.zeros(HIDDEN, F)) and policy.status == 1
        assert np.array_equal(policy(row), clean[k])


@pytest.mark.parametrize(
    ("change", "message"),
    [
        ({"direction": "bidirectional"}, "only direction=forward"),
        ({"activations": ["Tanh", "Tanh", "Tanh"]}, "only the default activations"),
        ({"input_forget": 1}, "input_forget=1"),
    ],
)
def test_an_unsupported_cell_is_refused_in_one_line(change: dict[str, object], message: str) -> None:
    model = _cell_model("LSTM")
    cell = model.graph.node[1]
    cell.attribute.extend(helper.make_attribute(k, v) for k, v in change.items())
    with pytest.raises(UnsupportedOpError, match=message) as info:
        to_ir(model)
    assert "\n" not in str(info.value)


def test_a_state_input_without_its_next_value_is_refused() -> None:
    model = _cell_model("LSTM")
    del model.graph.output[2]  # c_next is no longer an output: c has no next value
    with pytest.raises(UnsupportedOpError, match="one more output per further input"):
        to_ir(model)
    swapped = _cell_model("GRU")
    swapped.graph.output[1].CopyFrom(helper.make_tensor_value_info("act", TensorProto.FLOAT, [1, HIDDEN]))
    swapped.graph.output[0].CopyFrom(
        helper.make_tensor_value_info("h_next", TensorProto.FLOAT, [1, 1, HIDDEN])
    )
    # pairs by position (the output order is the contract): h with act, which onnxruntime could not feed back
    with pytest.raises(UnsupportedOpError, match=r"'h' \[1, 1, 16\] and its next value, output 'act'"):
        to_ir(swapped)


def lstm_state_of_another_rank() -> onnx.ModelProto:
    """An LSTM cell whose next hidden state leaves as [1, 16]: its input h is [1, 1, 16] (the same size)."""
    model = _cell_model("LSTM")
    graph = model.graph
    graph.node[1].output[1] = "h_cell"
    graph.initializer.append(numpy_helper.from_array(np.array([1, HIDDEN], np.int64), "rank2"))
    graph.node.append(helper.make_node("Reshape", ["h_cell", "rank2"], ["h_next"]))
    graph.output[1].CopyFrom(helper.make_tensor_value_info("h_next", TensorProto.FLOAT, [1, HIDDEN]))
    return model


def test_a_state_output_of_the_right_size_and_another_rank_is_refused() -> None:
    with pytest.raises(UnsupportedOpError, match="differ in shape") as info:
        to_ir(lstm_state_of_another_rank())
    assert "\n" not in str(info.value)


@pytest.mark.parametrize(("kind", "linear_before_reset"), [("LSTM", 0), ("GRU", 0), ("GRU", 1)])
def test_int8_recurrent_weights_are_bit_for_bit_their_model_over_a_sequence(
    kind: str, linear_before_reset: int, tmp_path: Path
) -> None:
    model = _cell_model(kind, linear_before_reset)
    graph = to_ir(model)
    check_supported(graph)
    obs = _observations(seed=5)
    c_dir = tmp_path / "c"
    c_dir.mkdir()
    for filename, text in generate(graph, "policy", quantize="int8-weights").items():
        (c_dir / filename).write_text(text)
    runs = {}
    for opt in ("-O0", "-O3"):
        build.make("lib", c_dir, tmp_path / opt, opt)
        policy = build.CPolicy(tmp_path / opt / "libpolicy.so", "policy", OBS, HIDDEN)
        runs[opt] = np.asarray([policy(row) for row in obs])
    assert np.array_equal(runs["-O0"], runs["-O3"])
    assert np.array_equal(runs["-O0"], quantize.evaluate(graph, obs))
    assert "static const int8_t policy_w" in (c_dir / "policy.c").read_text()
    # int8 weights move the hidden state by a little, not by a lot
    assert 0 < np.max(np.abs(runs["-O0"] - _ort_sequence(model, obs))) < 0.1


def test_q15_refuses_a_recurrent_cell_in_one_line(tmp_path: Path) -> None:
    from embedrl.export import fixed_point

    graph = to_ir(onnx.load(str(torch_recurrent_onnx("LSTM", tmp_path / "lstm.onnx"))))
    with pytest.raises(ExportError, match=r"LSTM node .* not supported with q15") as info:
        fixed_point.plan(graph, _observations())
    assert "\n" not in str(info.value)
