"""exp, tanh and sigmoid from IEEE float32 operations only: the NumPy model and the C, side by side.

libm's tanhf and expf differ between C libraries (newlib, glibc) and numpy, and a quantised policy must
equal its Python model bit for bit on the host and on Cortex-M; so quantised code uses these instead.
"""

from __future__ import annotations

import numpy as np

from embedrl.export.contract.literals import c_float
from embedrl.export.ops.base import F

EXP_CLAMP = (-87.0, 88.0)
"""exp_det's input range: beyond it float32 exp under- or overflows."""
TANH_SATURATION = 9.0
"""|x| above which tanh(x) rounds to +-1 in float32."""
LOG2E = F(1.44269504)
EXP2_POLY = tuple(
    F(c) for c in (1.0, 0.693147182, 0.240226507, 0.0555041087, 0.00961812911, 0.00133335581, 0.000154035304)
)
"""2^f for f in [-1/2, 1/2], Horner coefficients from degree 0 up (Taylor series; rel. error < 2e-7)."""


def exp_det(x: np.ndarray) -> np.ndarray:
    """exp in float32 IEEE operations only (mirrors the generated C's ``exp_det``); NaN gives NaN."""
    x = np.asarray(x, F)
    nan = np.isnan(x)
    return np.where(nan, x, _exp_finite(np.where(nan, F(0.0), x))).astype(F)


def _exp_finite(x: np.ndarray) -> np.ndarray:
    x = np.clip(x, F(EXP_CLAMP[0]), F(EXP_CLAMP[1]))
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


def helper_source(prefix: str, name: str) -> str:
    """C of the deterministic helper ``name`` (``exp_det``, ``tanh_det``, ``sigmoid_det``), operation by
    operation the NumPy functions above."""
    if name == "exp_det":
        lo, hi = c_float(EXP_CLAMP[0]), c_float(EXP_CLAMP[1])
        steps = "\n".join(f"    p = (p * f) + {c_float(float(c))};" for c in reversed(EXP2_POLY[:-1]))
        return f"""/* exp(x) from IEEE float operations only: the same bits anywhere. */
static float {prefix}_exp_det(float x)
{{
    union {{
        float f;
        uint32_t u;
    }} in;
    in.f = x;
    if ((in.u & 0x7fffffffu) > 0x7f800000u) {{
        return x; /* NaN stays NaN (and is never converted to an integer) */
    }}
    const float clamped = (x < {lo}) ? {lo} : ((x > {hi}) ? {hi} : x);
    const float t = clamped * {c_float(float(LOG2E))};
    const float t_half = t + 0.5f;
    int32_t n = (int32_t)t_half;
    if ((float)n > t_half) {{
        n -= 1; /* floor(t + 1/2): f stays within [-1/2, 1/2] */
    }}
    const float f = t - (float)n;
    float p = {c_float(float(EXP2_POLY[-1]))};
{steps}
    union {{
        uint32_t u;
        float f;
    }} two_n;
    two_n.u = ((uint32_t)n + 127u) << 23u; /* 2^n exactly: n is within [-125, 127], n + 127 within [2, 254] */
    return p * two_n.f;
}}"""
    if name == "tanh_det":
        return f"""static float {prefix}_tanh_det(float x)
{{
    const float a = (x < 0.0f) ? -x : x;
    float t = 1.0f - (2.0f / ({prefix}_exp_det(a + a) + 1.0f));
    t = (a > {c_float(TANH_SATURATION)}) ? 1.0f : t;
    return (x < 0.0f) ? -t : t;
}}"""
    return f"""static float {prefix}_sigmoid_det(float x)
{{
    return 1.0f / (1.0f + {prefix}_exp_det(-x));
}}"""
