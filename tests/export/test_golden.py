"""Golden files: the generated C for a tiny fixture is fixed, byte for byte.

A refactor must not change them. Regenerate only on purpose: ``pytest --regen-golden``.
"""

from __future__ import annotations

import subprocess
from pathlib import Path

import numpy as np
import onnx
import pytest
from onnx import helper

from embedrl.export.codegen import generate
from embedrl.export.contract.literals import c_float
from embedrl.export.onnx_import import to_ir
from tests.export.helpers import make_model

GOLDEN = Path(__file__).parent / "golden" / "tiny"
F = np.float32


def tiny_model() -> onnx.ModelProto:
    """3 -> 4 -> 2 with normalisation, ReLU, tanh and a clip: one of each common step."""
    rng = np.random.default_rng(1234)
    mk = helper.make_node
    nodes = [
        mk("Sub", ["x", "mean"], ["a"], name="normalize.sub"),
        mk("Div", ["a", "std"], ["b"], name="normalize.div"),
        mk("Gemm", ["b", "W1", "b1"], ["c"], name="fc1", transB=1),
        mk("Relu", ["c"], ["d"], name="relu1"),
        mk("Gemm", ["d", "W2", "b2"], ["e"], name="fc2", transB=1),
        mk("Tanh", ["e"], ["f"], name="squash"),
        mk("Clip", ["f", "lo", "hi"], ["y"], name="clip"),
    ]
    inits = {
        "mean": rng.normal(size=3).astype(F),
        "std": (rng.random(3) + 0.5).astype(F),
        "W1": rng.normal(size=(4, 3)).astype(F),
        "b1": rng.normal(size=4).astype(F),
        "W2": rng.normal(size=(2, 4)).astype(F),
        "b2": np.array([0.1, -0.2], F),
        "lo": F(-0.9),
        "hi": F(0.9),
    }
    return make_model(nodes, inits, 3, 2)


def test_generated_code_matches_the_golden_files(request: pytest.FixtureRequest) -> None:
    files = generate(to_ir(tiny_model()), provenance={"source": "tests/export/test_golden.py tiny_model()"})
    if request.config.getoption("--regen-golden"):
        GOLDEN.mkdir(parents=True, exist_ok=True)
        for name, text in files.items():
            (GOLDEN / name).write_text(text)
    assert sorted(files) == sorted(p.name for p in GOLDEN.iterdir())
    for name, text in files.items():
        assert text == (GOLDEN / name).read_text(), f"{name} differs from its golden file"


@pytest.mark.parametrize("source", ["policy.c", "policy_host.c"])
def test_golden_files_compile_standalone_with_strict_flags(tmp_path: Path, source: str) -> None:
    cmd = [
        "cc",
        "-std=c99",
        "-Wall",
        "-Wextra",
        "-Wconversion",
        "-Wdouble-promotion",
        "-Wcast-qual",
        "-Wshadow",
        "-Werror",
        "-pedantic",
        "-c",
        str(GOLDEN / source),
        "-o",
        str(tmp_path / "policy.o"),
    ]
    subprocess.run(cmd, check=True, capture_output=True)


def test_generation_is_deterministic() -> None:
    a = generate(to_ir(tiny_model()))
    b = generate(to_ir(tiny_model()))
    assert a == b
    assert "20" not in a["policy.h"].split("Do not edit")[0]  # no date or time in the banner


def test_no_malloc_no_stdio_and_named_layers() -> None:
    source = generate(to_ir(tiny_model()))["policy.c"]
    for forbidden in ("malloc", "free(", "stdio", "printf"):
        assert forbidden not in source
    for layer in ("Gemm 'fc1' [1x3] -> [1x4]", "Relu 'relu1'", "Tanh 'squash'", "Clip 'clip'"):
        assert layer in source
    assert "fc1 weights, input-major [3][4]" in source


def test_name_prefixes_every_symbol(tmp_path: Path) -> None:
    files = generate(to_ir(tiny_model()), name="left")
    assert sorted(files) == ["left.c", "left.h", "left_host.c", "left_host.h"]
    assert "#define LEFT_OBS_DIM 3u" in files["left.h"] and "int32_t left_step(" in files["left.h"]
    assert "policy" not in files["left.c"].split("*/", 1)[1]
    # Two policies link into one program.
    for name in ("left", "right"):
        for filename, text in generate(to_ir(tiny_model()), name=name).items():
            (tmp_path / filename).write_text(text)
    (tmp_path / "main.c").write_text(
        '#include "left.h"\n#include "right.h"\n'
        "int main(void) { float o[3] = {0}, a[2], b[2]; return left_step(o, a) + right_step(o, b); }\n"
    )
    subprocess.run(
        [
            "cc",
            "-std=c99",
            "-Wall",
            "-Wextra",
            "-Werror",
            "-pedantic",
            "-o",
            str(tmp_path / "two"),
            str(tmp_path / "main.c"),
            str(tmp_path / "left.c"),
            str(tmp_path / "right.c"),
            "-lm",
        ],
        check=True,
        capture_output=True,
    )
    assert subprocess.run([str(tmp_path / "two")]).returncode == 0


def test_weights_are_stored_input_major_and_round_trip_exactly() -> None:
    model = tiny_model()
    w1 = onnx.numpy_helper.to_array(next(i for i in model.graph.initializer if i.name == "W1"))
    source = generate(to_ir(model))["policy.c"]
    block = source.split("fc1 weights, input-major [3][4] */")[1].split("};")[0]
    literals = [t.strip() for t in block.replace("{", " ").replace("}", " ").split("=")[1].split(",")]
    values = np.array([np.float32(float(t.rstrip("f"))) for t in literals if t], dtype=F)
    assert values.tobytes() == np.ascontiguousarray(w1.T).tobytes()
    assert c_float(1.0) == "1.0f" and c_float(-0.0) == "-0.0f" and c_float(1e-30) == "1e-30f"
