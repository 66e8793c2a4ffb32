"""The policy an export's generated C reproduces, rebuilt from the export folder alone.

float32: the export's ``policy.onnx`` under onnxruntime (the C agrees within the verification
tolerance), a recurrent policy's state carried from call to call as the C carries it
(:class:`OnnxPolicy`). int8, int8-weights and q15: the Python model of the quantised arithmetic
(:func:`export.quantize.evaluate`),
which the C equals bit for bit; an integer section (int8, q15) is planned again from the export's own
calibration observations (``test/observations.npy``), exactly as the export planned it.
"""

from __future__ import annotations

import json
from collections.abc import Callable
from pathlib import Path
from typing import Any

import numpy as np
import onnx

from embedrl.export import interpret, qdq, quantize
from embedrl.export.errors import ExportError
from embedrl.export.interpret import Section
from embedrl.export.ir import Graph
from embedrl.export.onnx_import import load_onnx

REPORT_FILE = "export_report.json"
OBSERVATIONS_FILE = "observations.npy"
"""The verification observations (float32), in the export's ``test/``."""
PRECISIONS = ("float32", "int8", "int8-weights", "q15")

Policy = Callable[[np.ndarray], np.ndarray]


def precision_of(export_dir: Path) -> str:
    """``float32``, ``int8``, ``int8-weights`` or ``q15``, as the export's report records it (float32
    without a report)."""
    report = export_dir / REPORT_FILE
    if not report.is_file():
        return "float32"
    try:
        content = json.loads(report.read_text())
        quantized = content.get("quantize")
    except (OSError, ValueError, AttributeError) as exc:
        raise ExportError(f"{report}: not readable ({exc})") from None
    precision = quantized or "float32"
    if precision not in PRECISIONS:
        raise ExportError(f"{report}: unknown precision {precision!r}; known: {', '.join(PRECISIONS)}")
    check_scheme(content, report)
    return str(precision)


def check_scheme(content: Any, report: Path) -> None:
    """The scheme the report names is the one its verification describes: an export whose ``quantize``
    names another scheme than this tool's of that name (``int8`` once named the weight-only scheme) is
    refused, not run under the wrong arithmetic."""
    name = content.get("quantize")
    try:
        described = content["verification"]["quantization"]["scheme"]
    except (KeyError, TypeError):
        return
    if name in quantize.SCHEMES and described != quantize.SCHEMES[name]:
        raise ExportError(
            f"{report}: its '{name}' is {described!r}, not this tool's {name} ({quantize.SCHEMES[name]}); "
            "export the policy again"
        )


class OnnxPolicy:
    """An ONNX policy under onnxruntime, called with one observation [obs_dim] or a batch [B, obs_dim].

    A policy without memory answers each row on its own (row by row when the file fixes its batch at 1). A
    recurrent one (state inputs after the observation, paired in order with the outputs after the action)
    carries its state from call to call as the generated C does: a batch is consecutive steps, and
    :meth:`reset` starts a new episode from zero state.
    """

    def __init__(self, model: onnx.ModelProto | Path) -> None:
        import onnxruntime as ort

        source = str(model) if isinstance(model, Path) else model.SerializeToString()
        self._session = ort.InferenceSession(source, providers=["CPUExecutionProvider"])
        inputs = self._session.get_inputs()
        self._name = inputs[0].name
        self._fixed_batch = inputs[0].shape[0] == 1
        self._state_inputs = [(i.name, [d if isinstance(d, int) else 1 for d in i.shape]) for i in inputs[1:]]
        self.recurrent = bool(self._state_inputs)
        self._state: dict[str, np.ndarray] = {}
        self.reset()

    def reset(self) -> None:
        """A new episode: the recurrent state back to zero (nothing for a policy without memory)."""
        self._state = {name: np.zeros(shape, np.float32) for name, shape in self._state_inputs}

    def __call__(self, obs: np.ndarray) -> np.ndarray:
        batch = np.asarray(obs, dtype=np.float32)
        single = batch.ndim == 1
        rows = batch.reshape(1, -1) if single else batch
        if self.recurrent or self._fixed_batch:
            out = np.concatenate([self._step(row[None]) for row in rows]) if len(rows) else rows[:, :0]
        else:
            out = np.asarray(self._session.run(None, {self._name: rows})[0], np.float32)
        return out.reshape(-1) if single else out

    def _step(self, row: np.ndarray) -> np.ndarray:
        outputs = self._session.run(None, {self._name: row, **self._state})
        self._state = dict(zip(self._state, (np.asarray(o, np.float32) for o in outputs[1:]), strict=True))
        return np.asarray(outputs[0], np.float32).reshape(1, -1)


def reference_policy(export_dir: Path) -> Policy:
    """A batch policy ``[B, obs_dim] -> [B, act_dim]`` (float32) that the export's C reproduces (for a
    recurrent policy an :class:`OnnxPolicy`, with its ``reset``)."""
    onnx_path = export_dir / "policy.onnx"
    precision = precision_of(export_dir)
    if precision == "float32":
        return OnnxPolicy(onnx_path)
    graph, given = qdq.lowered(load_onnx(onnx_path))
    section = None
    if precision in quantize.SECTIONS:
        observations = export_dir / "test" / OBSERVATIONS_FILE
        if not observations.is_file():
            raise ExportError(
                f"{export_dir}: no test/{OBSERVATIONS_FILE} to plan the {precision} section from"
            )
        section = quantize.plan_section(graph, precision, np.load(observations, allow_pickle=False), given)

    return QuantizedPolicy(graph, section)


class QuantizedPolicy:
    """The Python model of a quantised export's arithmetic as a policy: a batch [B, obs_dim] of independent
    rows, or for a recurrent graph consecutive steps with the state carried (``reset``: zero state)."""

    def __init__(self, graph: Graph, section: Section | None) -> None:
        self.graph, self.section = graph, section
        self._state: dict[str, np.ndarray] = {}

    def reset(self) -> None:
        self._state = {}

    def __call__(self, obs: np.ndarray) -> np.ndarray:
        batch = np.asarray(obs, np.float32).reshape(-1, self.graph.size(self.graph.input))
        if not self.graph.states:
            return np.asarray(quantize.evaluate(self.graph, batch, self.section), np.float32)
        rows = []
        for row in batch:
            values = interpret.run(self.graph, row[None], "int8", state=self._state)
            self._state = {read: values[write] for read, write in self.graph.states}
            rows.append(values[self.graph.output].reshape(-1))
        return np.asarray(rows, np.float32)
