"""A QDQ-quantised ONNX from elsewhere (onnxruntime's ``quantize_static``) exports to int8 C that runs
the model's own int8 weights and activation scales, verified against onnxruntime running that QDQ model;
what the integer C cannot run is refused in one line."""

from __future__ import annotations

import json
import re
from collections.abc import Callable
from pathlib import Path

import numpy as np
import onnx
import pytest
from onnx import numpy_helper
from onnxruntime.quantization import QuantType

from embedrl.cli import main
from embedrl.export import qdq
from embedrl.export.full_integer import SCHEME, IntegerSection
from embedrl.export.quantize import plan_section
from embedrl.export.regenerate import mismatch, regenerate
from tests.export.helpers import quantized
from tests.hil.conftest import SHIPPED_TD3


@pytest.fixture(scope="module", params=[True, False], ids=["per channel", "per tensor"])
def qdq_model(
    exported: Callable[..., Path], tmp_path_factory: pytest.TempPathFactory, request: pytest.FixtureRequest
) -> Path:
    float_export = exported(SHIPPED_TD3, "--episodes", "0")
    return quantized(float_export, tmp_path_factory.mktemp("qdq") / "td3 qdq.onnx", per_channel=request.param)


@pytest.fixture(scope="module")
def qdq_export(exported: Callable[..., Path], qdq_model: Path) -> Path:
    return exported(qdq_model, "--scenario", "static", "--episodes", "10")


def test_the_qdq_export_runs_the_models_own_int8_numbers(qdq_model: Path, qdq_export: Path) -> None:
    report = json.loads((qdq_export / "export_report.json").read_text())
    assert report["quantize"] == SCHEME
    model = onnx.load(str(qdq_model))
    graph, given = qdq.lowered(model)
    assert given is not None
    observations = np.load(qdq_export / "test" / "observations.npy")
    section = plan_section(graph, SCHEME, observations, given)
    assert isinstance(section, IntegerSection) and len(section.layers) == 3
    weights = {i.name: numpy_helper.to_array(i) for i in model.graph.initializer}
    for layer, index in zip(section.layers, (0, 2, 4), strict=True):
        own = weights[f"actor_mu_{index}_weight_quantized"]  # [out][in], onnxruntime's int8 weights
        assert own.dtype == np.int8 and np.array_equal(layer.weights, own)
    scales = {n.input[0]: weights[n.input[1]] for n in model.graph.node if n.op_type == "QuantizeLinear"}
    assert section.quant.scale == pytest.approx(float(scales["obs"]), rel=1e-7)


def test_the_qdq_export_is_verified_against_onnxruntime_running_it(qdq_export: Path) -> None:
    checks = json.loads((qdq_export / "export_report.json").read_text())["verification"]
    quantization = checks["quantization"]
    assert quantization["model_mismatches"] == 0  # the C equals its integer model bit for bit
    found = quantization["qdq"]
    assert found["reference"] == "onnxruntime running the QDQ model"
    assert found["layers"] == ["obs", "actor_mu_0", "actor_mu_2", "actor_mu_4"]  # names as identifiers
    assert max(found["max_layer_steps"]) <= found["tolerance_steps"] == qdq.MAX_LAYER_STEPS == 1.0
    assert found["max_layer_steps"][0] == 0  # the input is quantised as the model quantises it
    assert 0 < found["end_to_end_max_output_steps"] < 3
    if _vnni():  # against the QDQ model's actions as onnxruntime computes them
        assert quantization["worst_action_error_vs_float"] < 0.2
    else:  # onnxruntime's u8 x s8 kernel without VNNI (vpmaddubsw) saturates pair sums at int16
        assert quantization["worst_action_error_vs_float"] < 2.0
    loop = json.loads((qdq_export / "export_report.json").read_text())["closed_loop"]
    assert loop["episodes"] == 10 and loop["differing_outcomes"] == 0


def _vnni() -> bool:
    """Whether this CPU has VNNI (AVX512-VNNI or AVX-VNNI): onnxruntime's int8 GEMM then sums exactly."""
    flags = Path("/proc/cpuinfo").read_text() if Path("/proc/cpuinfo").is_file() else ""
    return "avx512_vnni" in flags or "avx_vnni" in flags


def test_the_qdq_exports_c_is_generated_again_byte_for_byte(qdq_export: Path) -> None:
    assert mismatch(qdq_export) is None
    again = regenerate(qdq_export)
    assert not isinstance(again, str) and isinstance(again.section, IntegerSection)


def test_a_qdq_model_keeps_its_own_quantisation_and_refuses_another(
    qdq_model: Path, tmp_path: Path, capsys: pytest.CaptureFixture[str]
) -> None:
    for scheme in ("int8-weights", "q15"):
        assert main(["export", str(qdq_model), "--scenario", "static", "--out", str(tmp_path / scheme),
                     "--quantize", scheme, "--episodes", "0"]) == 2  # fmt: skip
        err = capsys.readouterr().err
        assert err.startswith("error: ") and err.count("\n") == 1 and f"not --quantize {scheme}" in err
        assert not (tmp_path / scheme).exists()


@pytest.mark.parametrize(
    ("activation", "extra", "refusal"),
    [
        (QuantType.QUInt8, {}, r"QuantizeLinear node '.*': activations need .* int8 zero point"),
        (
            QuantType.QInt8,
            {"per_channel": False, "extra_options": {"WeightSymmetric": False}},
            r"DequantizeLinear node '.*': constants must be int8",
        ),
    ],
    ids=["uint8 activations", "asymmetric weights"],
)
def test_a_qdq_model_the_integer_c_cannot_run_is_refused_naming_the_node(
    exported: Callable[..., Path],
    tmp_path: Path,
    capsys: pytest.CaptureFixture[str],
    activation: QuantType,
    extra: dict[str, object],
    refusal: str,
) -> None:
    source = quantized(exported(SHIPPED_TD3, "--episodes", "0"), tmp_path / "other.onnx", activation, **extra)
    out = tmp_path / "out"
    assert main(["export", str(source), "--scenario", "static", "--out", str(out), "--episodes", "0"]) == 2
    err = capsys.readouterr().err
    assert err.startswith("error: ") and err.count("\n") == 1, err
    assert re.search(refusal, err), err
    assert not out.exists()


def test_a_relu_fused_into_a_quantisation_is_put_back(qdq_model: Path) -> None:
    model = onnx.load(str(qdq_model))
    assert "Relu" not in {n.op_type for n in model.graph.node}  # onnxruntime's quantiser removed them
    float_model, given = qdq.split(model)
    ops = [n.op_type for n in float_model.graph.node]
    assert ops[:5] == ["Gemm", "Relu", "Gemm", "Relu", "Gemm"]
    assert given is not None and all(
        a.zero == qdq.INT8_MIN for k, a in given.activations.items() if k.endswith("_relu")
    )
    assert qdq.is_qdq(model) and not qdq.is_qdq(float_model)
    assert [n.op_type for n in model.graph.node] == [n.op_type for n in onnx.load(str(qdq_model)).graph.node]
