"""Building tiny ONNX graphs and compiling their generated C for the export tests."""

from __future__ import annotations

import itertools
from pathlib import Path
from typing import Any

import numpy as np
import onnx
from onnx import TensorProto, helper, numpy_helper
from onnxruntime.quantization import CalibrationDataReader, QuantFormat, QuantType, quantize_static

from embedrl.export import build
from embedrl.export.codegen import generate
from embedrl.export.onnx_import import to_ir

_counter = itertools.count()


def cpu_flags() -> set[str]:
    """This CPU's feature flags as ``/proc/cpuinfo`` lists them (empty where there is none)."""
    text = Path("/proc/cpuinfo").read_text() if Path("/proc/cpuinfo").exists() else ""
    line = next((row for row in text.splitlines() if row.startswith("flags")), "")
    return set(line.split(":", 1)[-1].split())


def make_model(
    nodes: list[onnx.NodeProto],
    inits: dict[str, Any],
    in_dim: int,
    out_dim: int,
    in_shape: list[int | str] | None = None,
    opset: int = 17,
) -> onnx.ModelProto:
    """A model with input 'x' [batch, in_dim] and output 'y' [batch, out_dim]."""
    graph = helper.make_graph(
        nodes,
        "test",
        [helper.make_tensor_value_info("x", TensorProto.FLOAT, in_shape or ["batch", in_dim])],
        [helper.make_tensor_value_info("y", TensorProto.FLOAT, ["batch", out_dim])],
        [numpy_helper.from_array(np.asarray(v), k) for k, v in inits.items()],
    )
    return helper.make_model(graph, opset_imports=[helper.make_opsetid("", opset)], ir_version=8)


def compile_model(
    model: onnx.ModelProto, tmp: Path, name: str = "policy", opt: str | None = None
) -> build.CPolicy:
    """Generate C for ``model``, build it with make (optionally at optimisation ``opt``), and load it."""
    graph = to_ir(model)
    folder = tmp / f"m{next(_counter)}"
    c_dir = folder / "c"
    c_dir.mkdir(parents=True)
    for filename, text in generate(graph, name).items():
        (c_dir / filename).write_text(text)
    build.make("lib", c_dir, folder / "build", opt)
    return build.CPolicy(
        folder / "build" / "libpolicy.so", name, graph.size(graph.input), graph.size(graph.output)
    )


def mlp_model(widths: list[int], acts: list[str] | None = None, seed: int = 0) -> onnx.ModelProto:
    """A Gemm MLP with random weights (seeded): ``acts`` per layer, default ReLU hidden and tanh out."""
    acts = acts or ["Relu"] * (len(widths) - 2) + ["Tanh"]
    rng = np.random.default_rng(seed)
    nodes, inits, last = [], {}, "x"
    for i, (n_in, n_out) in enumerate(itertools.pairwise(widths)):
        inits[f"W{i}"] = rng.normal(scale=1 / np.sqrt(n_in), size=(n_out, n_in)).astype(np.float32)
        inits[f"b{i}"] = rng.normal(scale=0.1, size=n_out).astype(np.float32)
        nodes.append(helper.make_node("Gemm", [last, f"W{i}", f"b{i}"], [f"g{i}"], transB=1))
        out = "y" if i == len(acts) - 1 else f"a{i}"
        nodes.append(helper.make_node(acts[i], [f"g{i}"], [out]))
        last = out
    return make_model(nodes, inits, widths[0], widths[-1])


CALIBRATION_ROWS = 256
"""Observations onnxruntime's quantiser calibrates on (the float export's verification observations)."""


class Rows(CalibrationDataReader):  # type: ignore[misc]  # onnxruntime has no type information
    """The float export's observations, one row per calibration step."""

    def __init__(self, name: str, rows: np.ndarray) -> None:
        self._feeds = iter([{name: rows[i : i + 1]} for i in range(len(rows))])

    def get_next(self) -> dict[str, np.ndarray] | None:
        return next(self._feeds, None)


def quantized(float_export: Path, out: Path, activation: QuantType = QuantType.QInt8, **kw: object) -> Path:
    """The float export's policy.onnx quantised by onnxruntime (QDQ, per channel unless ``kw`` says)."""
    rows = np.load(float_export / "test" / "observations.npy")[:CALIBRATION_ROWS].astype(np.float32)
    source = float_export / "policy.onnx"
    name = onnx.load(str(source)).graph.input[0].name
    options = {"per_channel": True, "weight_type": QuantType.QInt8, **kw}
    quantize_static(
        str(source), str(out), Rows(name, rows), quant_format=QuantFormat.QDQ, activation_type=activation,
        **options,
    )  # fmt: skip
    return out
