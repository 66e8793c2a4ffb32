"""Quantised models as other tools write them: a static batch of 1 (``torch.onnx.export`` without dynamic
axes) exports and verifies; scales the integer C cannot use (float16, zero, negative) are refused in one
line naming the node."""

from __future__ import annotations

import json
from collections.abc import Callable
from pathlib import Path

import numpy as np
import onnx
import pytest
from onnx import TensorProto, numpy_helper

from embedrl.cli import main
from tests.export.helpers import quantized

SHIPPED_TD3 = Path(__file__).resolve().parents[2] / "policies" / "static" / "td3.zip"


@pytest.fixture(scope="module")
def qdq(exported: Callable[..., Path], tmp_path_factory: pytest.TempPathFactory) -> Path:
    return quantized(exported(SHIPPED_TD3, "--episodes", "0"), tmp_path_factory.mktemp("qdq") / "qdq.onnx")


def _export(source: Path, out: Path) -> int:
    return main(["export", str(source), "--scenario", "static", "--out", str(out), "--episodes", "0"])


def test_a_static_batch_of_one_exports_and_verifies(qdq: Path, tmp_path: Path) -> None:
    model = onnx.load(str(qdq))
    for value in (*model.graph.input, *model.graph.output):
        dim = value.type.tensor_type.shape.dim[0]
        dim.ClearField("dim_param")
        dim.dim_value = 1
    source = tmp_path / "batch one.onnx"
    onnx.save(model, str(source))
    assert _export(source, tmp_path / "out") == 0
    quantization = json.loads((tmp_path / "out" / "export_report.json").read_text())["verification"][
        "quantization"
    ]
    assert quantization["model_mismatches"] == 0 and max(quantization["qdq"]["max_layer_steps"]) <= 1.0


def _first_weight_scale(model: onnx.ModelProto) -> onnx.TensorProto:
    inits = {i.name: i for i in model.graph.initializer}
    int8 = {name for name, init in inits.items() if init.data_type == TensorProto.INT8}
    node = next(n for n in model.graph.node if n.op_type == "DequantizeLinear" and n.input[0] in int8)
    scale: onnx.TensorProto = inits[node.input[1]]
    return scale


@pytest.mark.parametrize(
    ("change", "message"),
    [
        (lambda a: a.astype(np.float16), "its scale is float16; the int8 export takes float32 scales"),
        (
            lambda a: np.where(np.arange(a.size) == 0, 0.0, a).astype(np.float32),
            "must be finite and positive",
        ),
        (lambda a: -a, "must be finite and positive"),
        (lambda a: np.full_like(a, np.nan), "must be finite and positive"),
    ],
)
def test_a_scale_the_integer_c_cannot_use_is_refused(
    qdq: Path, tmp_path: Path, capsys: pytest.CaptureFixture[str], change: Callable[[np.ndarray], np.ndarray],
    message: str,
) -> None:  # fmt: skip
    model = onnx.load(str(qdq))
    scale = _first_weight_scale(model)
    scale.CopyFrom(numpy_helper.from_array(change(numpy_helper.to_array(scale)), scale.name))
    source = tmp_path / "bad.onnx"
    onnx.save(model, str(source))
    assert _export(source, tmp_path / "out") == 2
    err = capsys.readouterr().err
    assert err.startswith("error: DequantizeLinear node ") and message in err and err.count("\n") == 1, err
    assert not (tmp_path / "out").exists()
