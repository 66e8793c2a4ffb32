"""The policy an export's generated C reproduces, rebuilt from the export folder alone.

float32: the export's ``policy.onnx`` under onnxruntime (the C agrees within the verification
tolerance). int8 and q15: the Python model of the quantised arithmetic (:func:`export.quantize.evaluate`),
which the C equals bit for bit; q15's fixed-point section is planned again from the export's own
calibration observations (``test/observations.npy``), exactly as the export planned it.
"""

from __future__ import annotations

import json
from collections.abc import Callable
from pathlib import Path

import numpy as np

from embedrl.export import fixed_point, quantize
from embedrl.export.errors import ExportError
from embedrl.export.onnx_import import load_onnx, to_ir

REPORT_FILE = "export_report.json"
OBSERVATIONS_FILE = "observations.npy"
"""The verification observations (float32), in the export's ``test/``."""
PRECISIONS = ("float32", "int8", "q15")

Policy = Callable[[np.ndarray], np.ndarray]


def precision_of(export_dir: Path) -> str:
    """``float32``, ``int8`` or ``q15``, as the export's report records it (float32 without a report)."""
    report = export_dir / REPORT_FILE
    if not report.is_file():
        return "float32"
    try:
        quantized = json.loads(report.read_text()).get("quantize")
    except (OSError, ValueError, AttributeError) as exc:
        raise ExportError(f"{report}: not readable ({exc})") from None
    precision = quantized or "float32"
    if precision not in PRECISIONS:
        raise ExportError(f"{report}: unknown precision {precision!r}; known: {', '.join(PRECISIONS)}")
    return str(precision)


def reference_policy(export_dir: Path) -> Policy:
    """A batch policy ``[B, obs_dim] -> [B, act_dim]`` (float32) that the export's C reproduces."""
    onnx_path = export_dir / "policy.onnx"
    precision = precision_of(export_dir)
    if precision == "float32":
        import onnxruntime as ort

        session = ort.InferenceSession(str(onnx_path), providers=["CPUExecutionProvider"])
        name = session.get_inputs()[0].name

        def run_onnx(obs: np.ndarray) -> np.ndarray:
            return np.asarray(session.run(None, {name: np.asarray(obs, np.float32)})[0], np.float32)

        return run_onnx
    graph = to_ir(load_onnx(onnx_path))
    section = None
    if precision == "q15":
        observations = export_dir / "test" / OBSERVATIONS_FILE
        if not observations.is_file():
            raise ExportError(f"{export_dir}: no test/{OBSERVATIONS_FILE} to plan the q15 section from")
        section = fixed_point.plan(graph, np.load(observations, allow_pickle=False))

    def run_quantized(obs: np.ndarray) -> np.ndarray:
        batch = np.asarray(obs, np.float32).reshape(-1, graph.size(graph.input))
        return np.asarray(quantize.evaluate(graph, batch, section), np.float32)

    return run_quantized
