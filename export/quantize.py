"""``--quantize int8``: int8 weights per output channel, float32 activations, and the exact model.

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
:func:`evaluate` here and the generated C give bit-identical actions on the host and on Cortex-M.
"""

from __future__ import annotations

import numpy as np

from embedrl.export import fixed_point
from embedrl.export.errors import UnsupportedOpError
from embedrl.export.fixed_point import FixedSection
from embedrl.export.ir import Graph

F = np.float32
SCHEMES = {
    "int8": "int8 weights per output channel (symmetric), float32 activations",
    "q15": "16-bit fixed point: int16 weights (per-channel power-of-two scales) and activations, int64 sums",
}
INT8_MAX = 127
EXP_CLAMP = (-87.0, 88.0)
"""exp_det's input range: beyond it float32 exp under- or overflows."""
TANH_SATURATION = 9.0
"""|x| above which tanh(x) rounds to +-1 in float32."""
LOG2E = F(1.44269504)
EXP2_POLY = tuple(
    F(c) for c in (1.0, 0.693147182, 0.240226507, 0.0555041087, 0.00961812911, 0.00133335581, 0.000154035304)
)
"""2^f for f in [-1/2, 1/2], Horner coefficients from degree 0 up (Taylor series; rel. error < 2e-7)."""
SUPPORTED = frozenset(
    {
        "Gemm",
        "MatMul",
        "Add",
        "Sub",
        "Mul",
        "Div",
        "Max",
        "Min",
        "Relu",
        "LeakyRelu",
        "Tanh",
        "Sigmoid",
        "Clip",
        "Identity",
        "Flatten",
        "Reshape",
        "Constant",
    }
)


def quantize_columns(w: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """Input-major float weights [K][N] -> (int8 [K][N], float32 scale [N]), symmetric per output."""
    peak = np.max(np.abs(w), axis=0).astype(F)
    scale = np.where(peak > 0, peak / F(INT8_MAX), F(1.0)).astype(F)
    q = np.clip(np.rint(w / scale), -INT8_MAX, INT8_MAX).astype(np.int8)
    return q, scale


def exp_det(x: np.ndarray) -> np.ndarray:
    """exp in float32 IEEE operations only (mirrors the generated C's ``exp_det``)."""
    x = np.clip(np.asarray(x, F), F(EXP_CLAMP[0]), F(EXP_CLAMP[1]))
    t = (x * LOG2E).astype(F)
    n = np.floor((t + F(0.5)).astype(F)).astype(F)  # nearest integer: f stays within [-1/2, 1/2]
    f = (t - n).astype(F)
    p = np.full_like(f, EXP2_POLY[-1])
    for c in reversed(EXP2_POLY[:-1]):
        p = (p * f + c).astype(F)
    return (p * np.ldexp(F(1.0), n.astype(np.int32)).astype(F)).astype(F)


def tanh_det(x: np.ndarray) -> np.ndarray:
    x = np.asarray(x, F)
    a = np.abs(x)
    e = exp_det((a + a).astype(F))
    t = (F(1.0) - F(2.0) / (e + F(1.0))).astype(F)
    t = np.where(a > F(TANH_SATURATION), F(1.0), t).astype(F)
    return np.where(x < 0, -t, t).astype(F)


def sigmoid_det(x: np.ndarray) -> np.ndarray:
    return (F(1.0) / (F(1.0) + exp_det(-np.asarray(x, F)))).astype(F)


def check_supported(graph: Graph) -> None:
    for node in graph.nodes:
        if node.op not in SUPPORTED:
            raise UnsupportedOpError(
                f"{node.op} node '{node.name}' is not supported with --quantize int8; "
                f"supported: {', '.join(sorted(SUPPORTED))}"
            )


def _layer(x: np.ndarray, w: np.ndarray, bias: np.ndarray | None) -> np.ndarray:
    """One quantised layer over a batch: rows are independent, each in the C's operation order."""
    q, scale = quantize_columns(w)
    qf = q.astype(F)
    acc = np.zeros((x.shape[0], w.shape[1]), F)
    for k in range(w.shape[0]):
        acc = (acc + (x[:, k : k + 1] * qf[k]).astype(F)).astype(F)
    scaled = (scale * acc).astype(F)
    return scaled if bias is None else (bias + scaled).astype(F)


def evaluate(graph: Graph, obs: np.ndarray, section: FixedSection | None = None) -> np.ndarray:
    """The quantised policy's actions for a batch of observations [B, obs_dim], bit-exact with the C.

    Without ``section`` the int8 scheme; with it, the q15 section replaces its nodes.
    """
    values: dict[str, np.ndarray] = {graph.input: np.asarray(obs, F).reshape(len(obs), -1)}

    def get(name: str) -> np.ndarray:
        return values[name] if name in values else np.asarray(graph.constants[name], F).reshape(-1)

    for node in graph.nodes:
        if section is not None and node.name in section.nodes:
            if node.name == section.first_node:
                values[section.output] = fixed_point.run(section, get(section.input))
            continue
        x = get(node.inputs[0])
        op = node.op
        if op in ("Gemm", "MatMul"):
            b = graph.constants[node.inputs[1]].astype(F)
            trans = op == "Gemm" and bool(node.attr("transB", 0))
            w = np.ascontiguousarray(b.T if trans else b)
            has_c = op == "Gemm" and len(node.inputs) > 2 and bool(node.inputs[2])
            c = graph.constants[node.inputs[2]].astype(F).reshape(-1) if has_c else None
            if c is not None and c.size == 1:
                c = np.full(w.shape[1], c[0], F)
            if float(node.attr("alpha", 1.0)) != 1.0 or float(node.attr("beta", 1.0)) != 1.0:
                raise UnsupportedOpError(
                    f"Gemm node '{node.name}': alpha/beta != 1 are not supported with --quantize"
                )
            y = _layer(x, w, c)
        elif op in ("Add", "Sub", "Mul", "Div", "Max", "Min"):
            b = get(node.inputs[1])
            fn = {
                "Add": np.add,
                "Sub": np.subtract,
                "Mul": np.multiply,
                "Div": np.divide,
                "Max": np.fmax,
                "Min": np.fmin,
            }[op]
            y = fn(x, b[0] if b.size == 1 else b.reshape(1, -1) if b.ndim == 1 else b).astype(F)
        elif op == "Relu":
            y = np.where(x > 0, x, F(0.0)).astype(F)
        elif op == "LeakyRelu":
            y = np.where(x >= 0, x, (F(node.attr("alpha", 0.01)) * x).astype(F)).astype(F)
        elif op == "Tanh":
            y = tanh_det(x)
        elif op == "Sigmoid":
            y = sigmoid_det(x)
        elif op == "Clip":
            y = x.copy()
            for k, bound in enumerate(node.inputs[1:3]):
                if bound:
                    v = F(graph.constants[bound].reshape(-1)[0])
                    y = np.where(y < v, v, y) if k == 0 else np.where(y > v, v, y)
            y = y.astype(F)
        elif op in ("Identity", "Flatten", "Reshape"):
            y = x
        else:
            raise UnsupportedOpError(f"{op} node '{node.name}' is not supported with --quantize int8")
        values[node.outputs[0]] = y
    return values[graph.output]
