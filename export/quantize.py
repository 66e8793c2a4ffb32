"""``--quantize int8-weights``: int8 weights per output channel, float32 activations, and the exact model.

(``--quantize int8`` is the full-integer scheme, :mod:`embedrl.export.full_integer`; this one keeps what it
cannot run: recurrent cells, non-ReLU hidden activations, policies too coarse for int8 activations.)

Scheme: each Gemm/MatMul weight column (one output) is scaled symmetrically to int8,
``q = round(w / s)`` with ``s = max|w| / 127``; the layer computes ``acc = sum_k x[k] * q[k][n]`` in
float32 (inputs in order, as in the float code) and ``y[n] = b[n] + s[n] * acc[n]``.

Why float activations: the weights are over 95% of the flash and int8 weights cut them 4x, which
meets the flash budget; on a Cortex-M4F a float multiply-add costs what an integer one does; and
float activations need no calibration, so accuracy is that of the weights alone. FPU-less cores
pay for software floating point (see the size report) .

Exactness: every operation is an IEEE-754 float32 operation in a fixed order (no FMA: C99 mode
keeps gcc from contracting), and tanh and sigmoid use :func:`exp_det`, an exp built from IEEE
operations only instead of libm (whose tanhf differs between newlib, glibc and numpy). So
:func:`evaluate` here and the generated C give bit-identical actions on the host and on Cortex-M. The
arithmetic of each op lives with the op (:mod:`embedrl.export.ops`); this module is the scheme's entry.
"""

from __future__ import annotations

from collections.abc import Callable

import numpy as np

from embedrl.export import fixed_point, full_integer, interpret
from embedrl.export.errors import UnsupportedOpError
from embedrl.export.interpret import Section
from embedrl.export.ir import Graph
from embedrl.export.ops import EMITTERS

WEIGHTS_ONLY = "int8-weights"
"""The weight-only scheme's name (this module)."""
RENAMED = {"int8-full": full_integer.SCHEME}
"""Former scheme names the command line still accepts, and the scheme each now names."""
SCHEMES = {
    full_integer.SCHEME: "full-integer int8: int8 weights (per-channel symmetric) and activations "
    "(calibrated scale and zero point), int32 sums, gemmlowp requantisation",
    WEIGHTS_ONLY: "int8 weights per output channel (symmetric), float32 activations",
    "q15": "16-bit fixed point: int16 weights (per-channel power-of-two scales) and activations, int64 sums",
}
SECTIONS: dict[str, Callable[[Graph, np.ndarray], Section]] = {
    "q15": fixed_point.plan,
    full_integer.SCHEME: full_integer.plan,
}
"""Schemes that run the layer chain as an integer section, and how each plans it from calibration
observations."""


def plan_section(
    graph: Graph, scheme: str | None, calibration: np.ndarray, given: full_integer.Given | None = None
) -> Section | None:
    """The scheme's integer section calibrated on ``calibration`` (None for float32 and int8-weights), or,
    for int8, quantised as ``given`` (a QDQ model's own quantisation)."""
    if given is not None:
        if scheme != full_integer.SCHEME:
            raise UnsupportedOpError(
                f"a QDQ-quantised ONNX carries its own int8 quantisation: export it with --quantize "
                f"{full_integer.SCHEME} or without --quantize, not {scheme or 'float32'}"
            )
        return full_integer.plan(graph, np.asarray(calibration, np.float32), given)
    planner = SECTIONS.get(scheme or "")
    return None if planner is None else planner(graph, np.asarray(calibration, np.float32))


SUPPORTED = frozenset(op for op, emitter in EMITTERS.items() if emitter.quantizable)
"""Ops with quantised code and an exact int8 model (each op says so itself)."""


def check_supported(graph: Graph) -> None:
    for node in graph.nodes:
        if node.op not in SUPPORTED:
            raise UnsupportedOpError(
                f"{node.op} node '{node.name}' is not supported with --quantize {WEIGHTS_ONLY}; "
                f"supported: {', '.join(sorted(SUPPORTED))}"
            )


def evaluate(graph: Graph, obs: np.ndarray, section: Section | None = None) -> np.ndarray:
    """The quantised policy's actions for a batch of observations [B, obs_dim], bit-exact with the C.

    Without ``section`` the int8-weights scheme; with it, the integer section (int8, q15) replaces its
    nodes. A recurrent graph takes the rows as one sequence from zero state.
    """
    if graph.states:
        return interpret.run_sequence(graph, obs, "int8")
    return interpret.run(graph, obs, "int8", section)[graph.output]
