"""tanh and sigmoid in int16 for ``--quantize int8``'s last layer: the table, the integer model and the C.

The method of TFLite's int16 Tanh and Logistic and of CMSIS-NN's ``arm_nn_activation_s16``: a table of the
function on non-negative inputs, linear interpolation between its entries, the sign by symmetry, and both
functions from one table (``sigmoid(x) = (1 + tanh(x / 2)) / 2``). Their table has 256 entries (512 B);
this one 33 (66 B), a step of 1/8 over [0, 4]:

- the input ``t`` is int16 in Q3.12 (``x = t / 4096``, [-8, 8)), the last layer's sums requantised to it
  (for sigmoid to ``x / 2``);
- ``a = |t|``; at ``a >= 4 * 4096`` the last entry (tanh(4)), else entry ``a >> 9`` plus the difference to
  the next times ``a & 511``, rounded half up by ``>> 9``; negated for ``t < 0``: ``r`` in Q15;
- the float at the API is exact: ``r / 32768`` (tanh), ``(32768 + r) / 65536`` (sigmoid).

Worst error against float64 tanh over every int16 input: 1.51e-3 (:data:`TANH_WORST_ERROR`; the chords
between entries, and tanh(4)'s 6.7e-4 from 1 beyond); sigmoid half of it. The requantisation into Q3.12
adds at most half a step of the input (1/8192, 1.2e-4 after tanh). All arithmetic is integer: the C and
:func:`squash_model` give the same bits.
"""

from __future__ import annotations

import numpy as np

FRAC = 12
"""Fractional bits of the int16 input (Q3.12)."""
STEP_BITS = 9
"""Input steps per table segment, as a power of two: segments of 2^9 / 2^12 = 1/8."""
SEGMENTS = 32
"""Segments of the table: [0, 32 / 8] = [0, 4]."""
ONE = 1 << 15
"""1.0 in the Q15 output."""
INT16_MIN, INT16_MAX = -(1 << 15), (1 << 15) - 1
TABLE = np.round(ONE * np.tanh(np.arange(SEGMENTS + 1) * 2.0 ** (STEP_BITS - FRAC))).astype(np.int64)
"""tanh at 0, 1/8, ..., 4 in Q15 (int16)."""
TANH_WORST_ERROR = 1.51e-3
"""Worst |table tanh - tanh| over every int16 input (the test recomputes it)."""
SQUASHES = {"Tanh": 1, "Sigmoid": 2}
"""The ops this runs, and the factor the input's scale carries for each (sigmoid's table input is x / 2)."""


def input_step(op: str) -> float:
    """The real value of one step of the int16 input for ``op``."""
    return SQUASHES[op] * 2.0**-FRAC


def tanh_q15(t: np.ndarray) -> np.ndarray:
    """The table's tanh of int16 inputs ``t`` (int64 arrays): Q15, as the C computes it."""
    a = np.abs(t)
    i = np.minimum(a >> STEP_BITS, SEGMENTS)
    low, high = TABLE[i], TABLE[np.minimum(i + 1, SEGMENTS)]
    frac = a & ((1 << STEP_BITS) - 1)
    y = np.where(
        i >= SEGMENTS, TABLE[SEGMENTS], low + (((high - low) * frac + (1 << (STEP_BITS - 1))) >> STEP_BITS)
    )
    return np.asarray(np.where(t < 0, -y, y), np.int64)


def squash_model(t: np.ndarray, op: str) -> np.ndarray:
    """``op`` (a key of :data:`SQUASHES`) of int16 inputs as float32, bit for bit the C's."""
    r = tanh_q15(t)
    if op == "Tanh":
        return np.asarray(r.astype(np.float32) * np.float32(1.0 / ONE), np.float32)
    return np.asarray((ONE + r).astype(np.float32) * np.float32(0.5 / ONE), np.float32)


def tanh_source(prefix: str) -> str:
    """The C of :func:`tanh_q15` (int32 holding an int16 in, Q15 out) and its table."""
    entries = ", ".join(str(int(v)) for v in TABLE)
    return f"""/* tanh at 0, 1/8, ..., 4 in Q15: the int16 tanh and sigmoid interpolate between these. */
static const int16_t {prefix}_tanh_table[{SEGMENTS + 1}] = {{
    {entries}
}};

/* tanh of t / 4096 (t an int16) in Q15: linear between the table's entries, its last entry from 4 on, odd.
 * Worst error against tanh: {TANH_WORST_ERROR:.3g}. */
static int32_t {prefix}_tanh_q15(int32_t t)
{{
    const uint32_t a = (t < 0) ? (uint32_t)(-t) : (uint32_t)t;
    const uint32_t i = a >> {STEP_BITS}u;
    uint32_t y = (uint32_t){prefix}_tanh_table[{SEGMENTS}];
    if (i < {SEGMENTS}u) {{
        const uint32_t low = (uint32_t){prefix}_tanh_table[i];
        const uint32_t rise = (uint32_t){prefix}_tanh_table[i + 1u] - low;
        y = low + (((rise * (a & {(1 << STEP_BITS) - 1}u)) + {1 << (STEP_BITS - 1)}u) >> {STEP_BITS}u);
    }}
    return (t < 0) ? -(int32_t)y : (int32_t)y;
}}"""


def squash_c(prefix: str, op: str, t: str) -> str:
    """The C expression of :func:`squash_model` of the int16 value ``t``: a float."""
    if op == "Tanh":
        return f"(float){prefix}_tanh_q15({t}) * {1.0 / ONE:.9g}f"
    return f"(float)({ONE} + {prefix}_tanh_q15({t})) * {0.5 / ONE:.9g}f"
