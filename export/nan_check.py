"""NaN propagation, op by op: every computing op of an export, alone, against onnxruntime.

A policy whose C turns a NaN into a finite number (``x > 0 ? x : 0``, ``fmaxf``) hides a fault: the step's
final finite check then sees a plausible action. Sampled observations rarely reach the region where a
network produces NaN, so this check puts it there. Each op of the graph is generated as a one-op module
without the step's finite checks (``generate(checks=False)``), in the export's precision, and compiled
with the Makefile's compiler and flags; its runtime input gets a NaN at each position in turn (the other
elements finite), and the elements of its output that are NaN must be exactly those ONNX's own reference
(``onnx.reference``) gives for the same one-op model, and include every NaN of onnxruntime (whose LSTM and
GRU kernels return finite numbers for a NaN input: the C is the stricter of the two there). Finite elements
are compared with onnxruntime within the export's tolerance for float32 (int8 and q15 round their
weights: only the NaN pattern is compared there).

Ops that are the same data under another shape (Identity, Reshape, ...) compute nothing and are not
probed; ops of a q15 section compute in integers, which hold no NaN: the section's float input is checked
before it is converted (the C returns the safe action), which the generated code's tests cover. An op with
a second runtime operand other than a recurrent state has no one-input module and is listed as skipped.
"""

from __future__ import annotations

import ctypes
import shlex
import subprocess
from collections.abc import Sequence
from pathlib import Path
from typing import Any

import numpy as np
import onnx
from onnx import helper, numpy_helper

from embedrl.common import owned_temporary_folder
from embedrl.export import build
from embedrl.export.codegen import HOST_SUFFIX, generate
from embedrl.export.errors import BuildError, VerificationError
from embedrl.export.ir import Graph, Node
from embedrl.export.ops import EMITTERS
from embedrl.export.quantize import WEIGHTS_ONLY
from embedrl.export.verify import TOLERANCE

FINITE_SCALE = 0.5
"""Standard deviation of the finite elements around the NaN (float32 normal, seeded)."""
MAX_POSITIONS = 512
"""Positions probed per op: all of them up to this many, else this many spread evenly."""
PROBE_FLAGS = ("-Wno-unused-function", "-fPIC", "-shared")
"""The probe modules leave the finite checks out, so their finite helper is unused."""


def check(
    graph: Graph,
    quantize: str | None,
    opset: int,
    section_nodes: frozenset[str] = frozenset(),
    tolerance: float = TOLERANCE,
    seed: int = 0,
) -> dict[str, Any]:
    """Probe every computing op of ``graph``; raise :class:`VerificationError` at the first op whose C and
    onnxruntime disagree on which outputs are NaN. Returns what was probed (for the export report)."""
    probes, skipped = _probes(graph, section_nodes)
    summary: dict[str, Any] = {
        "ops": len(probes),
        "positions": 0,
        "integer_ops": len(section_nodes),
        "skipped": skipped,
        "rule": "one op at a time, a NaN at each input position: the C's NaN outputs are ONNX's reference's "
        "and include onnxruntime's; ops of a q15 section compute in integers (their float input is checked)",
    }
    if not probes:
        return summary
    rng = np.random.default_rng(seed)
    # The float ops around an integer section (q15, int8) are the int8-weights scheme's.
    precision = None if quantize is None else WEIGHTS_ONLY
    with owned_temporary_folder("embedrl-nan-") as tmp:
        library = _compile([_one_op(graph, node, k, precision) for k, node in enumerate(probes)], Path(tmp))
        for k, node in enumerate(probes):
            summary["positions"] += _probe(
                library, k, graph, node, opset, rng, tolerance if quantize is None else None
            )
    return summary


def _probes(graph: Graph, section_nodes: frozenset[str]) -> tuple[list[Node], list[str]]:
    probes, skipped = [], []
    for node in graph.nodes:
        emitter = EMITTERS[node.op]
        if emitter.alias or node.op == "Constant" or node.name in section_nodes:
            continue
        if _states(graph, node) is None:
            skipped.append(f"{node.op} '{node.name}': a second runtime operand (covered by the op's tests)")
            continue
        probes.append(node)
    return probes, skipped


def _states(graph: Graph, node: Node) -> tuple[tuple[str, str], ...] | None:
    """A recurrent op's state inputs paired with its later outputs of the same shape (the module carries
    them as its state, zero at reset); None if the op has another runtime operand."""
    extra = [i for i in node.inputs[1:] if i and not graph.is_constant(i)]
    later = [o for o in node.outputs[1:] if o]
    if not extra:
        return ()
    pairs = tuple(zip(extra, later[: len(extra)], strict=False))
    if len(pairs) < len(extra) or any(graph.shapes[i] != graph.shapes[o] for i, o in pairs):
        return None
    return pairs


def _one_op(graph: Graph, node: Node, k: int, precision: str | None) -> dict[str, str]:
    states = _states(graph, node) or ()
    used = [v for v in (*node.inputs, *node.outputs) if v]
    single = Graph.freeze(
        node.inputs[0],
        node.outputs[0],
        [node],
        {v: graph.shapes[v] for v in used},
        {v: graph.constants[v] for v in node.inputs if v and graph.is_constant(v)},
        states,
    )
    return generate(single, f"nan_op{k}", provenance={"probe": node.name}, quantize=precision, checks=False)


def _compile(modules: Sequence[dict[str, str]], folder: Path) -> ctypes.CDLL:
    sources = []
    for files in modules:
        for filename, text in files.items():
            (folder / filename).write_text(text)
            if filename.endswith(".c") and not filename.endswith(HOST_SUFFIX):  # the step only
                sources.append(str(folder / filename))
    command = [
        *shlex.split(build.compiler()["command"]),
        *PROBE_FLAGS,
        "-o",
        str(folder / "probes.so"),
    ]
    result = subprocess.run([*command, *sources, "-lm"], capture_output=True, text=True)
    if result.returncode != 0:
        tail = "\n".join(result.stderr.strip().splitlines()[-10:])
        raise BuildError(f"building the NaN-propagation probes failed:\n{tail}")
    return ctypes.CDLL(str(folder / "probes.so"))


def _probe(
    library: ctypes.CDLL,
    k: int,
    graph: Graph,
    node: Node,
    opset: int,
    rng: np.random.Generator,
    tolerance: float | None,
) -> int:
    """Probe one op at each input position; the number of positions."""
    n_in, n_out = graph.size(node.inputs[0]), graph.size(node.outputs[0])
    step, reset = getattr(library, f"nan_op{k}_step"), getattr(library, f"nan_op{k}_reset")
    pointer = ctypes.POINTER(ctypes.c_float)
    step.argtypes, step.restype = [pointer, pointer], ctypes.c_int
    reset.argtypes, reset.restype = [], None
    session, reference = _sessions(graph, node, opset)
    base = (rng.standard_normal(n_in) * FINITE_SCALE).astype(np.float32)
    positions = (
        np.arange(n_in) if n_in <= MAX_POSITIONS else np.linspace(0, n_in - 1, MAX_POSITIONS).astype(int)
    )
    states = _states(graph, node) or ()
    for position in positions:
        x = base.copy()
        x[position] = np.nan
        out = np.zeros(n_out, np.float32)
        reset()
        step(x.ctypes.data_as(pointer), out.ctypes.data_as(pointer))
        feeds = {node.inputs[0]: x.reshape(graph.shapes[node.inputs[0]])}
        feeds.update({read: np.zeros(graph.shapes[read], np.float32) for read, _ in states})
        expected = np.asarray(session.run([node.outputs[0]], feeds)[0], np.float32).reshape(-1)
        with np.errstate(invalid="ignore"):  # NaN in NumPy's functions is the point here
            meaning = np.asarray(reference.run([node.outputs[0]], feeds)[0], np.float32).reshape(-1)
        _compare(node, int(position), out, meaning, expected, tolerance)
    return len(positions)


def _compare(
    node: Node, position: int, c: np.ndarray, meaning: np.ndarray, ort: np.ndarray, tolerance: float | None
) -> None:
    where = f"{node.op} node '{node.name}' with NaN at input position {position}"
    for oracle, nan in (("ONNX's reference", np.isnan(meaning)), ("onnxruntime", np.isnan(ort))):
        wrong = nan & ~np.isnan(c) if oracle == "onnxruntime" else nan != np.isnan(c)
        if np.any(wrong):
            raise VerificationError(
                f"NaN propagation: {where}: the C gives NaN at outputs {_first(np.isnan(c))}, {oracle} at "
                f"{_first(nan)} (a NaN the C hides would leave the step as a plausible action)"
            )
    finite = ~np.isnan(ort) & ~np.isnan(c)
    if tolerance is not None and np.any(finite):
        error = np.abs(c[finite].astype(np.float64) - ort[finite])
        if np.any(error > tolerance * np.maximum(1.0, np.abs(ort[finite]))):
            raise VerificationError(
                f"NaN propagation: {where}: the finite outputs differ from onnxruntime by up to "
                f"{float(np.max(error)):.3g}"
            )


def _first(mask: np.ndarray) -> list[int]:
    return [int(i) for i in np.flatnonzero(mask)[:8]]


def _sessions(graph: Graph, node: Node, opset: int) -> tuple[Any, Any]:
    """onnxruntime and ONNX's reference evaluator on the one-op ONNX model of ``node`` (its constants as
    initializers)."""
    import onnxruntime as ort
    from onnx.reference import ReferenceEvaluator

    from embedrl.export.onnx_import import runtime_ir_version

    runtime = [v for v in node.inputs if v and not graph.is_constant(v)]
    constants = [v for v in node.inputs if v and graph.is_constant(v)]
    out = node.outputs[0]
    attrs: dict[str, Any] = {k: list(v) if isinstance(v, tuple) else v for k, v in node.attrs.items()}
    proto = helper.make_node(node.op, list(node.inputs), list(node.outputs), node.name, **attrs)
    model = helper.make_model(
        helper.make_graph(
            [proto],
            "nan_probe",
            [helper.make_tensor_value_info(v, onnx.TensorProto.FLOAT, graph.shapes[v]) for v in runtime],
            [helper.make_tensor_value_info(out, onnx.TensorProto.FLOAT, graph.shapes[out])],
            [numpy_helper.from_array(np.asarray(graph.constants[v]), v) for v in constants],
        ),
        opset_imports=[helper.make_opsetid("", opset)],
        ir_version=runtime_ir_version(),
    )
    options = ort.SessionOptions()
    options.graph_optimization_level = ort.GraphOptimizationLevel.ORT_DISABLE_ALL
    session = ort.InferenceSession(model.SerializeToString(), options, providers=["CPUExecutionProvider"])
    return session, ReferenceEvaluator(model)
