"""The speed benchmark runs and reports its ratios (no timing is asserted: benchmarks are not tests)."""

from __future__ import annotations

import json
from pathlib import Path

import numpy as np
import onnx
import pytest
from onnx import helper

from embedrl.cli import main
from embedrl.export.quantize import SCHEMES
from tests.export.helpers import make_model


def test_bench_export_reports_ratios_from_one_run(tmp_path: Path) -> None:
    w = np.random.default_rng(0).normal(size=(2, 6)).astype(np.float32)
    model = make_model(
        [helper.make_node("Gemm", ["x", "W"], ["g"], transB=1), helper.make_node("Tanh", ["g"], ["y"])],
        {"W": w},
        6,
        2,
    )
    onnx.save(model, str(tmp_path / "m.onnx"))
    assert main(["export", str(tmp_path / "m.onnx"), "--out", str(tmp_path / "exp"), "--episodes", "0"]) == 0
    out = tmp_path / "bench.json"
    assert main(["bench-export", "--export-dir", str(tmp_path / "exp"), "--json", str(out)]) == 0
    data = json.loads(out.read_text())
    assert data["c_ns_per_inference"] > 0 and data["onnxruntime_ns_per_inference"] > 0
    assert data["torch_ns_per_inference"] is None  # an ONNX source has no torch model
    assert data["speedup_vs_onnxruntime"] == pytest.approx(
        data["onnxruntime_ns_per_inference"] / data["c_ns_per_inference"], rel=0.01
    )
    assert data["object_text_bytes"] > 0
    # the limit, measured in the same run: the model's 12 multiply-adds and 48 weight bytes on this CPU
    assert data["model_multiply_adds"] == 12 and data["model_weight_bytes"] == 48 and data["cpu"]
    assert data["limit_ns"] == max(data["limit_fma_ns"], data["limit_weight_read_ns"]) > 0
    assert data["c_ratio_to_limit"] == pytest.approx(data["c_ns_per_inference"] / data["limit_ns"], rel=0.1)
    assert data["c_batched_ns_per_observation"] > 0 and data["emx_onnx_cgen_ns_per_inference"] is None
    assert data["c_native_ns_per_inference"] > 0 and data["c_native_max_abs_diff_from_c"] <= 1e-5
    assert (
        data["limit_without_fma_ns"] is None or data["limit_without_fma_ns"] >= data["limit_weight_read_ns"]
    )
    assert data["c_batched_ratio_to_onnxruntime_batched"] == pytest.approx(
        data["c_batched_ns_per_observation"] / data["onnxruntime_batched_ns_per_observation"], rel=0.1
    )
    assert (
        data["onnxruntime_max_abs_diff_from_c"] <= 1e-5 and data["onnxruntime_batched_ns_per_observation"] > 0
    )


@pytest.mark.parametrize("precision", sorted(SCHEMES))
def test_a_quantised_export_is_checked_against_its_own_reference(precision: str, tmp_path: Path) -> None:
    """Every quantised precision: the C must equal its precision's reference; its difference from the float
    peers is the quantisation's, reported and not refused; the limit reads the precision's weight bytes."""
    w = np.random.default_rng(1).normal(size=(2, 6)).astype(np.float32)
    model = make_model([helper.make_node("Gemm", ["x", "W"], ["y"], transB=1)], {"W": w}, 6, 2)
    onnx.save(model, str(tmp_path / "m.onnx"))
    args = ["export", str(tmp_path / "m.onnx"), "--out", str(tmp_path / "exp"), "--episodes", "0",
            "--obs-range=-1:1", "--act-range=-10:10", "--sample-time", "0.1"]  # fmt: skip
    assert main([*args, "--quantize", precision]) == 0
    out = tmp_path / "bench.json"
    assert main(["bench-export", "--export-dir", str(tmp_path / "exp"), "--json", str(out)]) == 0
    data = json.loads(out.read_text())
    assert data["precision"] == precision and data["reference_max_abs_diff_from_c"] <= 1e-5
    assert data["onnxruntime_max_abs_diff_from_c"] > 0
    assert data["model_weight_bytes"] == 12 * {"int8": 1, "int8-weights": 1, "q15": 2}[precision]


def test_bench_export_needs_an_export_folder(tmp_path: Path, capsys: pytest.CaptureFixture[str]) -> None:
    assert main(["bench-export", "--export-dir", str(tmp_path)]) == 2
    assert "not an export folder" in capsys.readouterr().err


def _fake_emx(folder: Path, offset: str) -> Path:
    """A stand-in for emx-onnx-cgen's command line: its C answers through the export's own step (plus
    ``offset``), so the harness, the time and the agreement check are tested without the peer installed."""
    script = folder / "emx"
    script.write_text(
        "#!/bin/sh\n"
        "# emx-onnx-cgen compile MODEL OUT --model-name peer\n"
        f"cat > \"$3\" <<'C'\n"
        '#include "policy.c"\n'
        "void peer(int batch, const float obs[][POLICY_OBS_DIM], float act[][POLICY_ACT_DIM])\n"
        "{\n"
        "    for (int i = 0; i < batch; ++i) {\n"
        "        (void)policy_step(obs[i], act[i]);\n"
        f"        act[i][0] += {offset};\n"
        "    }\n"
        "}\n"
        "C\n"
    )
    script.chmod(0o755)
    return script


def test_bench_export_times_emx_onnx_cgen_in_the_same_harness_and_checks_its_actions(
    tmp_path: Path, capsys: pytest.CaptureFixture[str]
) -> None:
    model = make_model(
        [helper.make_node("Gemm", ["x", "W"], ["y"], transB=1)], {"W": np.eye(2, 6, dtype=np.float32)}, 6, 2
    )
    onnx.save(model, str(tmp_path / "m.onnx"))
    assert main(["export", str(tmp_path / "m.onnx"), "--out", str(tmp_path / "exp"), "--episodes", "0"]) == 0
    bench = ["bench-export", "--export-dir", str(tmp_path / "exp"), "--json", str(tmp_path / "b.json")]
    assert main([*bench, "--emx", str(_fake_emx(tmp_path, "0.0f"))]) == 0
    data = json.loads((tmp_path / "b.json").read_text())
    assert data["emx_onnx_cgen_max_abs_diff_from_c"] == 0.0
    assert data["emx_onnx_cgen_ns_per_inference"] > 0 and data["emx_onnx_cgen_batched_ns_per_observation"] > 0
    assert data["speedup_vs_emx_onnx_cgen"] == pytest.approx(
        data["emx_onnx_cgen_ns_per_inference"] / data["c_ns_per_inference"], rel=0.01
    )
    capsys.readouterr()
    (tmp_path / "b.json").unlink()
    assert main([*bench, "--emx", str(_fake_emx(tmp_path, "1e-3f"))]) == 2  # a peer computing another policy
    assert "emx_onnx_cgen_max_abs_diff_from_c" in capsys.readouterr().err
    assert not (tmp_path / "b.json").exists()
    assert main([*bench, "--emx", str(tmp_path / "nosuch")]) == 2
    assert "no emx-onnx-cgen at" in capsys.readouterr().err


def test_bench_export_times_a_quantised_export_against_its_float32_export(
    tmp_path: Path, capsys: pytest.CaptureFixture[str]
) -> None:
    """Both in the same harness in turn, the ratio of their medians printed; a float32-dir that is not the
    same policy's float32 export is refused before anything is measured."""
    model = make_model(
        [helper.make_node("Gemm", ["x", "W"], ["y"], transB=1)],
        {"W": np.random.default_rng(2).normal(size=(2, 6)).astype(np.float32)},
        6,
        2,
    )
    onnx.save(model, str(tmp_path / "m.onnx"))
    args = ["export", str(tmp_path / "m.onnx"), "--episodes", "0", "--obs-range=-1:1", "--act-range=-10:10",
            "--sample-time", "0.1"]  # fmt: skip
    assert main([*args, "--out", str(tmp_path / "float32")]) == 0
    assert main([*args, "--out", str(tmp_path / "int8"), "--quantize", "int8"]) == 0
    out = tmp_path / "bench.json"
    bench = ["bench-export", "--export-dir", str(tmp_path / "int8"), "--json", str(out)]
    assert main([*bench, "--float32-dir", str(tmp_path / "float32")]) == 0
    data = json.loads(out.read_text())
    assert data["float32_c_ns_per_inference"] > 0 and data["c_ns_per_inference_beside_float32"] > 0
    assert data["c_ratio_to_float32"] == pytest.approx(
        data["c_ns_per_inference_beside_float32"] / data["float32_c_ns_per_inference"], rel=0.01
    )
    out.unlink()
    capsys.readouterr()
    assert main([*bench, "--float32-dir", str(tmp_path / "int8")]) == 2
    assert "is not a float32 export (int8)" in capsys.readouterr().err
    float32_bench = ["bench-export", "--export-dir", str(tmp_path / "float32"), "--json", str(out)]
    assert main([*float32_bench, "--float32-dir", str(tmp_path / "float32")]) == 2
    assert "EXPORT_DIR is float32" in capsys.readouterr().err
    onnx.save(make_model([helper.make_node("Gemm", ["x", "W"], ["y"], transB=1)],
                         {"W": np.ones((2, 6), np.float32)}, 6, 2), str(tmp_path / "other.onnx"))  # fmt: skip
    other = ["export", str(tmp_path / "other.onnx"), *args[2:], "--out", str(tmp_path / "other")]
    assert main(other) == 0
    assert main([*bench, "--float32-dir", str(tmp_path / "other")]) == 2
    assert "exports another policy" in capsys.readouterr().err
    assert main(["bench-export", "--float32-dir", str(tmp_path / "float32")]) == 2
    assert "--float32-dir needs EXPORT_DIR" in capsys.readouterr().err
    assert not out.exists()
