"""Matrix products with constant weights: Gemm and MatMul, float32 or with int8 weights.

The weights are stored input-major (``W[k][n]``) so the inner loop runs over outputs and vectorises
without reassociating any sum: each output is summed in a fixed order, the same at every optimisation
level. On Cortex-M (scalar FPU or none) the same weights are read as dot products, several sums in
registers per pass (:func:`dot_order_source`), adding each output's terms in the same order: the same bits.
On a Cortex-M core with a single-precision FPU (GNU C) the dot products take their VLDM form
(:func:`vldm_source`): the weights stored in the order the passes read them, loaded by VLDM.
``--quantize int8``: each weight column (one output) is scaled symmetrically to int8,
``q = round(w / s)`` with ``s = max|w| / 127``; ``acc = sum_k x[k] * q[k][n]`` in float32 and
``y[n] = b[n] + s[n] * acc[n]``.
"""

from __future__ import annotations

import re
from collections.abc import Callable, Mapping, Sequence
from dataclasses import dataclass
from typing import ClassVar

import numpy as np

from embedrl.export.errors import UnsupportedOpError
from embedrl.export.ir import AttrValue, Node
from embedrl.export.ops.base import Affine, EmitContext, Emitter, F, Interval, Shape, _fail
from embedrl.export.ops.squash import INT16_MAX, INT16_MIN, squash_c, squash_model, tanh_source

INT8_MAX = 127


def quantize_columns(w: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """Input-major float weights [K][N] -> (int8 [K][N], float32 scale [N]), symmetric per output."""
    peak = np.max(np.abs(w), axis=0).astype(F)
    scale = np.where(peak > 0, peak / F(INT8_MAX), F(1.0)).astype(F)
    q = np.clip(np.rint(w / scale), -INT8_MAX, INT8_MAX).astype(np.int8)
    return q, scale


def int8_layer(x: np.ndarray, w: np.ndarray, bias: np.ndarray | None) -> np.ndarray:
    """One quantised layer over a batch: rows are independent, each in the C's operation order."""
    q, scale = quantize_columns(w)
    qf = q.astype(F)
    acc = np.zeros((x.shape[0], w.shape[1]), F)
    for k in range(w.shape[0]):
        acc = (acc + (x[:, k : k + 1] * qf[k]).astype(F)).astype(F)
    scaled = (scale * acc).astype(F)
    return scaled if bias is None else (bias + scaled).astype(F)


def _input_major(node: Node, b: np.ndarray, transposed: bool) -> np.ndarray:
    """Weights as ``W[k][n]`` (input-major): the inner loop runs over outputs and vectorises."""
    return np.ascontiguousarray(b.T if transposed else b, dtype=np.float32)


K_BLOCK = 4
"""Inputs folded into one pass over the outputs: fewer loads and stores of the accumulator row."""


def per_row(lines: list[str], rows: str | None) -> list[str]:
    """``lines`` once per row of a block (``rows`` its C row count), or as they are for one observation."""
    if rows is None:
        return lines
    return [f"for (uint32_t r = 0u; r < {rows}; ++r) {{", *(f"    {line}" for line in lines), "}"]


DOT_ROWS = (8, 4, 2, 1)
"""Outputs per pass of the dot-product order (:func:`dot_order_source`), largest first: 8 sums and the 8
weights of one input fit the Cortex-M4F's 32 single-precision registers. Measured in the VLDM form
(:func:`vldm_source`) on the study actor (Cortex-M4F cycle model): 8 per pass 41.1k cycles; 16 per pass (two
VLDM of 8 per input) 49.8k, its sums spilled to the stack."""


def dot_order_source(prefix: str) -> str:
    """The switch between the float loop orders, by target (see :func:`_matmul_lines`)."""
    return f"""/* Loop order of the float matrix products. On Cortex-M cores (a scalar FPU, or none): dot
 * products, each pass keeping {DOT_ROWS[0]} sums in registers for the whole input. Elsewhere: input-major,
 * the inner loop over the outputs, which vectorises. Both add each output's terms in the same order (its
 * initial value, then inputs 0, 1, ...): the same bits. */
#if defined(__ARM_ARCH_PROFILE) && (__ARM_ARCH_PROFILE == 'M')
#define {prefix.upper()}_DOT_PRODUCTS 1
#else
#define {prefix.upper()}_DOT_PRODUCTS 0
#endif"""


DOT_INPUTS_PER_ITERATION = 4
"""Inputs per iteration of a dot-product pass (unrolled; the rest after the loop): one loop test and branch
per four inputs. Measured on the study actor (Cortex-M4F cycle model, C loads): 1 per iteration 57.4k
cycles, 2: 54.5k, 4: 52.4k."""

VLDM_WEIGHT_REGISTER = 16
"""The first single-precision register of a pass's weights of one input in the VLDM form (s16-s23); an
iteration's inputs go from :data:`VLDM_INPUT_REGISTER` (s24-s27); the sums and products get the rest."""
VLDM_INPUT_REGISTER = 24


def vldm_condition(prefix: str) -> str:
    """When the float dot products take their VLDM form: a Cortex-M core (the dot-product order) with a
    single-precision FPU, GNU C (the inline assembly), and no -D<PREFIX>_PORTABLE. Compiler macros only: it
    also chooses the layout of the weights, which are declared before any macro of ours."""
    return (
        "defined(__ARM_ARCH_PROFILE) && (__ARM_ARCH_PROFILE == 'M') && defined(__GNUC__) "
        f"&& defined(__ARM_FP) && ((__ARM_FP & 4) != 0) && !defined({prefix.upper()}_PORTABLE)"
    )


def input_major_condition(prefix: str) -> str:
    """Where the float weights are compiled input-major: wherever the VLDM form is not."""
    return f"!({vldm_condition(prefix)})"


def vldm_source(prefix: str) -> str:
    """The switch of the VLDM form of the float dot products."""
    up = prefix.upper()
    return f"""/* The dot products' VLDM form, on a Cortex-M core with a single-precision FPU (GNU C): the
 * weights stored in the order the passes read them; each input's weights of a pass, and each iteration's
 * {DOT_INPUTS_PER_ITERATION} inputs, loaded by one VLDM: 1 + N cycles on the Cortex-M4 against 2 per VLDR
 * (ARM DDI 0439B, table 7-1), which is what gcc 12 emits for the C loads. The assembly sits in the
 * {prefix}_row<N> and {prefix}_inputs<N> functions only (MISRA C:2012 Dir 4.3); its GNU extensions (rule
 * 1.2) are compiled for GNU C only. Each output's terms are added in the C loops' order: the same bits.
 * -D{up}_PORTABLE: the C dot products on every core. */
#if {vldm_condition(prefix)}
#define {up}_VLDM 1
#else
#define {up}_VLDM 0
#endif"""


def floats_source(count: int) -> Callable[[str], str]:
    """``{prefix}_floats<count>``: the struct of ``count`` floats a VLDM function returns, one member each
    (``v0``, ``v1``, ...). Not an array member: cppcheck's MISRA addon reads ``const T w = f();`` of a struct
    whose member is an array as a partly initialised array (rule 9.3); the layout, and so the machine code,
    is the same."""

    def source(prefix: str) -> str:
        members = "\n".join(f"    float v{i};" for i in range(count))
        return f"""#if {prefix.upper()}_VLDM
typedef struct {{
{members}
}} {prefix}_floats{count};
#endif"""

    return source


def vldm_load_source(function: str, count: int, first: int) -> Callable[[str], str]:
    """``{prefix}_<function>``: the ``count`` floats at ``*p`` (a struct of :func:`floats_source`), by one
    VLDM into the registers from ``s<first>`` that advances ``*p`` past them (compiled where
    ``<PREFIX>_VLDM``)."""

    def source(prefix: str) -> str:
        regs = [f"s{first + i}" for i in range(count)]
        outputs = ", ".join(f'"=t"(v{i})' for i in range(count))
        values = ", ".join(f"v{i}" for i in range(count))
        return "\n".join(
            [
                f"#if {prefix.upper()}_VLDM",
                f"/* (*p)[0..{count - 1}] by one VLDM into {regs[0]}-{regs[-1]}, *p advanced past them.",
                " * volatile: the compiler keeps the loads in program order, so the next one waits for the",
                " * products of this one (no copies); memory: it reads memory. */",
                f"static inline {prefix}_floats{count} {prefix}_{function}(const float **p)",
                "{",
                "    const float *at = *p;",
                *(f'    register float v{i} __asm__("{reg}");' for i, reg in enumerate(regs)),
                f'    __asm__ volatile("vldmia %0!, {{{regs[0]}-{regs[-1]}}}"',
                f'                     : "+r"(at), {outputs}',
                "                     :",
                '                     : "memory");',
                "    *p = at;",
                f"    const {prefix}_floats{count} r = {{{values}}};",
                "    return r;",
                "}",
                "#endif",
            ]
        )

    return source


def pack_passes(w: np.ndarray) -> np.ndarray:
    """Input-major float weights [K][N] in the order the VLDM form's passes read them (:data:`DOT_ROWS`):
    pass by pass, input by input, the pass's weights of that input; the pass from output ``n`` starts at
    ``n * K``."""
    blocks, first = [], 0
    for r in DOT_ROWS:
        for _ in range((w.shape[1] - first) // r):
            blocks.append(w[:, first : first + r].reshape(-1))
            first += r
    return np.concatenate(blocks).astype(F)


@dataclass(frozen=True)
class VldmForm:
    """The VLDM form of a layer's dot products (:func:`vldm_source`)."""

    switch: str
    prefix: str
    inputs: bool
    """Whether the iterations load their inputs by VLDM (``{prefix}_inputs<N>``; a layer with at least
    :data:`DOT_INPUTS_PER_ITERATION` inputs)."""
    weights: str
    """The weights in the passes' order (:func:`pack_passes`)."""


@dataclass(frozen=True)
class DotOrder:
    """The loop orders of one observation's float matrix product besides input-major."""

    switch: str
    """The C switch of the dot-product order (:func:`dot_order_source`)."""
    vldm: VldmForm | None
    """Its VLDM form, for float weights."""


def _dot_input(r: int, xk: str, w_k: str, cast: str, vldm: VldmForm | None) -> list[str]:
    """One input's terms for the pass's ``r`` sums (``xk``: the input; ``w_k``: its row of input-major
    weights, C, read in C; in the ``vldm`` form, the pass's next ``r`` weights from its pointer ``wp``)."""
    lines = ["{", f"    const float xk = {xk};"]
    if vldm is None:
        ctype = "int8_t" if cast else "float"
        lines += [
            f"    const {ctype} *row = &{w_k}[n]; /* the pass's {r} weight(s) of this input */",
            *(f"    a{i} = a{i} + (xk * {cast}row[{i}]);" for i in range(r)),
        ]
    elif r == 1:
        lines += ["    const float w = *wp;", "    wp = &wp[1];", "    a0 = a0 + (xk * w);"]
    else:
        lines += [
            f"    const {vldm.prefix}_floats{r} w = {vldm.prefix}_row{r}(&wp);",
            *(f"    a{i} = a{i} + (xk * w.v{i});" for i in range(r)),
        ]
    return [*lines, "}"]


def _dot_lines(
    x: str, y: str, w: str, shape: tuple[int, int], init: str, cast: str, vldm: VldmForm | None
) -> list[str]:
    """Dot products over the input-major weights ``w[k][n]``, or in the ``vldm`` form over its weights
    (:func:`pack_passes`), in passes of :data:`DOT_ROWS` outputs; each sum in a register from ``init`` (C of
    output ``n``), then ``k = 0, 1, ...``: the input-major order's sums."""
    (k, n), lines, first = shape, [], 0
    step = 1 if cast else DOT_INPUTS_PER_ITERATION  # int8 weights: the scheme is for small flash, no unroll
    whole = k - k % step
    xs = [f"{x}[{_index('k', str(j))}]" for j in range(step)]
    head = []
    if vldm and vldm.inputs:
        xs = [f"xs.v{j}" for j in range(step)]
        head = [f"const {vldm.prefix}_floats{step} xs = {vldm.prefix}_inputs{step}(&xp);"]
    for r in DOT_ROWS:
        count = (n - first) // r
        if not count:
            continue
        at = [_index("n", str(i)) for i in range(r)]
        body = [
            *head,
            *(
                line
                for j in range(step)
                for line in _dot_input(r, xs[j], f"{w}[{_index('k', str(j))}]", cast, vldm)
            ),
        ]
        lines += [
            f"for (uint32_t n = {first}u; n < {first + r * count}u; n += {r}u) {{",
            *(f"    float a{i} = {init.replace('[n]', f'[{at[i]}]')};" for i in range(r)),
        ]
        if vldm:
            lines.append(f"    const float *wp = &{vldm.weights}[{_index(f'{k} * n')}]; /* input by input */")
        if head:
            lines.append(f"    const float *xp = {x};")
        if whole:
            lines += [
                f"    for (uint32_t k = 0u; k < {whole}u; k += {step}u) {{",
                *(f"        {b}" for b in body),
                "    }",
            ]
        for k0 in range(whole, k):
            lines += [f"    {b}" for b in _dot_input(r, f"{x}[{k0}]", f"{w}[{k0}]", cast, vldm)]
        lines += [*(f"    {y}[{at[i]}] = a{i};" for i in range(r)), "}"]
        first += r * count
    return lines


def _matmul_lines(
    x: str,
    y: str,
    w: str,
    k: int,
    n: int,
    init: str,
    cast: str = "",
    rows: str | None = None,
    order: DotOrder | None = None,
) -> list[str]:
    """``y = init + x @ w`` over input-major weights; for one observation with ``order`` (:func:`_order`) also
    the dot-product order (and its VLDM form, for float weights), chosen by the preprocessor."""
    lines = _input_major_lines(x, y, w, k, n, init, cast, rows)
    if rows is not None or order is None:
        return lines
    dots = [f"#if {order.switch}", *_dot_lines(x, y, w, (k, n), init, cast, None), "#else", *lines, "#endif"]
    if order.vldm is None:
        return dots
    vldm = _dot_lines(x, y, w, (k, n), init, cast, order.vldm)
    return [f"#if {order.vldm.switch}", *vldm, "#el" + dots[0][1:], *dots[1:]]


def _input_major_lines(
    x: str, y: str, w: str, k: int, n: int, init: str, cast: str, rows: str | None
) -> list[str]:
    # Per output the sum runs in a fixed order (init, then k = 0, 1, ...): the blocked pass
    # y[n] = y[n] + x0*w0[n] + x1*w1[n] + ... evaluates left to right, and vectorising over n
    # never reassociates it, so the result does not depend on the optimisation level or vector width.
    # In a block of rows the row loop runs inside the pass over k: each row's sums are the same, and the
    # K_BLOCK weight rows of a pass are read from memory once for the whole block.
    lines = per_row([f"for (uint32_t n = 0u; n < {n}u; ++n) {{", f"    {y}[n] = {init};", "}"], rows)
    full = k - k % K_BLOCK
    if full:
        ks = ["k", *(f"k + {j}u" for j in range(1, K_BLOCK))]  # no "k + 0": MISRA 2.2 (no effect)
        terms = " + ".join(f"(x{j} * {cast}{w}[{kj}][n])" for j, kj in enumerate(ks))
        block = [
            *[f"const float x{j} = {x}[{kj}];" for j, kj in enumerate(ks)],
            f"for (uint32_t n = 0u; n < {n}u; ++n) {{",
            f"    {y}[n] = {y}[n] + {terms};",
            "}",
        ]
        lines += [
            f"for (uint32_t k = 0u; k < {full}u; k += {K_BLOCK}u) {{",
            *(f"    {line}" for line in per_row(block, rows)),
            "}",
        ]
    for k0 in range(full, k):
        step = [
            f"for (uint32_t n = 0u; n < {n}u; ++n) {{",
            f"    {y}[n] = {y}[n] + ({x}[{k0}] * {cast}{w}[{k0}][n]);",
            "}",
        ]
        lines += per_row(step, rows)
    return lines


def _order(ctx: EmitContext, n: int, weights: tuple[str, np.ndarray, str] | None = None) -> DotOrder | None:
    """For one observation's code: the C switch choosing the float loop order (emitted once) and, for float
    ``weights`` (their key, input-major array and layer name), the VLDM form: its switch and load
    functions, and the weights in its passes' order, compiled where it is."""
    if ctx.rows is not None:
        return None
    switch = ctx.function("dot_products", dot_order_source).upper()
    if weights is None:
        return DotOrder(switch, None)
    vldm, (key, w, name), step = ctx.function("vldm", vldm_source).upper(), weights, DOT_INPUTS_PER_ITERATION
    left = n
    for r in DOT_ROWS:
        if r > 1 and left >= r:
            ctx.function(f"floats{r}", floats_source(r))
            ctx.function(f"row{r}", vldm_load_source(f"row{r}", r, VLDM_WEIGHT_REGISTER))
        left %= r
    inputs = w.shape[0] >= step
    if inputs:
        ctx.function(f"floats{step}", floats_source(step))
        ctx.function(f"inputs{step}", vldm_load_source(f"inputs{step}", step, VLDM_INPUT_REGISTER))
    packed = ctx.const(
        key + "#vldm",
        pack_passes(w),
        f"{name} weights [{w.shape[0]}][{n}] in the order the VLDM passes read them",
        vldm_condition(ctx.prefix),
    )
    return DotOrder(switch, VldmForm(vldm, ctx.prefix, inputs, packed))


def _quantized_lines(
    node: Node, ctx: EmitContext, w: np.ndarray, bias: str | None, x: str, y: str, n: int
) -> list[str]:
    """int8 weights per output channel: acc = sum x[k] * q[k][n]; y[n] = b[n] + s[n] * acc[n]."""
    q, scale = quantize_columns(w)
    k = w.shape[0]
    qsym = ctx.const(node.inputs[1] + "#int8", q, f"{node.name} weights, int8, input-major [{k}][{n}]")
    ssym = ctx.const(node.inputs[1] + "#scale", scale, f"{node.name} per-output scales [{n}]")
    lines = _matmul_lines(x, y, qsym, k, n, "0.0f", cast="(float)", rows=ctx.rows, order=_order(ctx, n))
    scaled = f"({ssym}[n] * {y}[n])"
    return [
        *lines,
        *per_row(
            [
                f"for (uint32_t n = 0u; n < {n}u; ++n) {{",
                f"    {y}[n] = {bias + ' + ' if bias else ''}{scaled};",
                "}",
            ],
            ctx.rows,
        ),
    ]


@dataclass(frozen=True)
class Q15Layer:
    """One Gemm or MatMul in 16-bit fixed point (planned by :func:`embedrl.export.fixed_point.plan`): its
    integer model (:meth:`reference`) and its C (:meth:`c_lines`), bit for bit the same arithmetic."""

    name: str
    weights: np.ndarray
    """int16 [N][K], output-major."""
    bias: np.ndarray
    """int64 [N], in accumulator units (in_frac + w_frac[n] fractional bits)."""
    w_frac: np.ndarray
    """Fractional bits of each output channel's weights [N]."""
    in_frac: int
    out_frac: int | None
    """Fractional bits of the int16 output; None for the last layer, whose output is float."""
    relu: bool

    def __post_init__(self) -> None:
        bound = int(np.max(np.abs(self.bias), initial=0)) + self.weights.shape[1] * Q15_MAX * Q15_MAX
        shifts = self.shifts() if self.out_frac is not None else np.ones(1, np.int64)
        if bound >= Q15_ACC_OFFSET or np.any(shifts < 1) or np.any(shifts > Q15_MAX_SHIFT):
            raise UnsupportedOpError(
                f"{self.name}: its q15 sums (up to {bound:.3g}) or rounding shifts (1..{Q15_MAX_SHIFT}) are "
                "out of range for 16-bit fixed point; export it in float32 or int8"
            )

    def shifts(self) -> np.ndarray:
        assert self.out_frac is not None
        return (self.in_frac + self.w_frac - self.out_frac).astype(np.int64)

    def out_scale(self) -> np.ndarray:
        """Last layer: float32 factor 2^-(in_frac + w_frac[n]) turning the accumulator into the output."""
        return np.ldexp(F(1.0), -(self.in_frac + self.w_frac).astype(np.int32)).astype(F)

    def reference(self, q: np.ndarray) -> np.ndarray:
        """The layer on a batch of int16 inputs (as int64): int16 outputs (as int64), or float32 for the last
        layer."""
        acc = q @ self.weights.astype(np.int64).T + self.bias
        if self.out_frac is None:
            return np.asarray(acc.astype(F) * self.out_scale(), dtype=F)
        s = self.shifts()
        r = np.clip((acc + (np.int64(1) << (s - 1))) >> s, -Q15_MAX, Q15_MAX)
        return np.asarray(np.maximum(r, 0) if self.relu else r)

    def c_lines(self, ctx: EmitContext, src: str, dst: str) -> list[str]:
        """C reading the int16 array ``src`` and writing ``dst`` (int16, or the float output if last)."""
        n_out, k_in = self.weights.shape
        w = ctx.const(
            f"{self.name}#q15", self.weights, f"{self.name} weights, int16, output-major [{n_out}][{k_in}]"
        )
        b = ctx.const(f"{self.name}#q15bias", self.bias, f"{self.name} bias in accumulator units [{n_out}]")
        lines = [
            f"/* {self.name}: [{k_in}] -> [{n_out}]{' + ReLU' if self.relu else ''} */",
            f"for (uint32_t n = 0u; n < {n_out}u; ++n) {{",
            f"    int64_t acc = {b}[n];",
            f"    for (uint32_t k = 0u; k < {k_in}u; ++k) {{",
            f"        const int32_t product = (int32_t){src}[k] * (int32_t){w}[n][k]; /* exact */",
            "        acc += product;",
            "    }",
        ]
        if self.out_frac is None:
            s = ctx.const(f"{self.name}#q15scale", self.out_scale(), f"{self.name} output scales [{n_out}]")
            return [*lines, f"    {dst}[n] = (float)acc * {s}[n];", "}"]
        sh = ctx.const(f"{self.name}#q15shift", self.shifts().astype(np.uint8), f"{self.name} shifts")
        clamp = "(r > 32767) ? 32767 : ((r < " + ("0) ? 0" if self.relu else "-32767) ? -32767") + " : r)"
        return [
            *lines,
            f"    const uint32_t sh = {sh}[n];",
            "    /* round: floor((acc + 2^(sh - 1)) / 2^sh), on acc + 2^62 (never negative), unsigned */",
            f"    const uint64_t offset = {Q15_ACC_OFFSET:#x}u;",
            "    const uint64_t one = 1u;",
            "    const uint32_t half_shift = sh - 1u;",
            "    const uint64_t half = one << half_shift;",
            "    const uint64_t biased = ((uint64_t)acc + offset) + half;",
            "    const uint64_t shifted = biased >> sh;",
            "    const uint64_t base = offset >> sh;",
            "    const int64_t r = (int64_t)shifted - (int64_t)base;",
            f"    {dst}[n] = (int16_t)({clamp});",
            "}",
        ]


Q15_MAX = 32767
"""int16 activations and weights are kept within +-Q15_MAX (symmetric)."""
Q15_ACC_OFFSET = 1 << 62
"""Added to a q15 sum before its rounding shift, so that the shift runs on an unsigned value (MISRA C:2012
rule 10.1: no shift of a signed value) and divides by 2^sh rounding down, as an arithmetic shift does: exact
for every sum within +-2^62, which each :class:`Q15Layer` checks of its weights and bias."""
Q15_MAX_SHIFT = 61
"""The largest rounding shift: 2^62 is a multiple of 2^sh, and the shifted sum stays below 2^63."""


class Linear(Emitter):
    """A matrix product with constant weights: its interval bounds come from :meth:`affine`, row by row;
    in q15 it runs as a :class:`Q15Layer`."""

    linear = True
    batched = True

    def bounds(self, node: Node, x: Interval, constants: Mapping[str, np.ndarray], size: int) -> Interval:
        a = self.affine(node, constants)
        w = a.weights.T  # [K, N]
        lo, hi = (v.reshape(-1, 1) for v in x)
        with np.errstate(invalid="ignore"):
            p, q = np.where(w == 0, 0.0, lo * w), np.where(w == 0, 0.0, hi * w)
        out_lo, out_hi = np.minimum(p, q).sum(axis=0), np.maximum(p, q).sum(axis=0)
        out_lo, out_hi = (
            np.minimum(a.alpha * out_lo, a.alpha * out_hi),
            np.maximum(a.alpha * out_lo, a.alpha * out_hi),
        )
        if a.bias is not None:
            out_lo, out_hi = out_lo + a.beta * a.bias, out_hi + a.beta * a.bias
        return out_lo, out_hi


class Gemm(Linear):
    """``Y = alpha * A @ op(B) + beta * C`` with A a runtime [1, K] row and B, C constants."""

    attrs: ClassVar[Mapping[str, AttrValue]] = {"alpha": 1.0, "beta": 1.0, "transA": 0, "transB": 0}
    min_inputs, max_inputs = 2, 3

    def shape(self, node: Node, shapes: Mapping[str, Shape], constants: Mapping[str, np.ndarray]) -> Shape:
        if int(node.attr("transA", 0)) != 0:
            raise _fail(node, "transA=1 is not supported (A is the observation row)")
        if int(node.attr("transB", 0)) not in (0, 1):
            raise _fail(node, f"transB must be 0 or 1, got {node.attr('transB', 0)}")
        a = shapes[node.inputs[0]]
        if len(a) != 2 or a[0] != 1:
            raise _fail(node, f"A must have shape [1, K], got {list(a)}")
        b_name = node.inputs[1]
        if b_name not in constants:
            raise _fail(node, f"B '{b_name}' must be a constant (weights as initializers)")
        b = constants[b_name]
        if b.ndim != 2:
            raise _fail(node, f"B must be 2-D, got shape {list(b.shape)}")
        k, n = (b.shape[1], b.shape[0]) if int(node.attr("transB", 0)) else b.shape
        if k != a[1]:
            raise _fail(node, f"A has {a[1]} columns but op(B) has {k} rows")
        if len(node.inputs) > 2 and node.inputs[2] != "":
            c_name = node.inputs[2]
            if c_name not in constants:
                raise _fail(node, f"C '{c_name}' must be a constant (bias as initializer)")
            if constants[c_name].size not in (1, n):
                raise _fail(node, f"C must have 1 or {n} elements, got shape {list(constants[c_name].shape)}")
        return (1, int(n))

    def affine(self, node: Node, constants: Mapping[str, np.ndarray]) -> Affine:
        b = constants[node.inputs[1]].astype(np.float64)
        weights = b if int(node.attr("transB", 0)) else b.T
        bias = None
        if len(node.inputs) > 2 and node.inputs[2]:
            bias = np.broadcast_to(
                constants[node.inputs[2]].astype(np.float64).reshape(-1), (weights.shape[0],)
            )
        return Affine(weights, bias, float(node.attr("alpha", 1.0)), float(node.attr("beta", 1.0)))

    def emit(self, node: Node, ctx: EmitContext, n: int) -> list[str]:
        b = ctx.constant(node.inputs[1])
        assert b is not None
        w = _input_major(node, b, bool(node.attr("transB", 0)))
        k = w.shape[0]
        wsym = (
            ""
            if ctx.quantize
            else ctx.const(
                node.inputs[1] + "#input-major",
                w,
                f"{node.name} weights, input-major [{k}][{n}]",
                input_major_condition(ctx.prefix),
            )
        )
        alpha, beta = float(node.attr("alpha", 1.0)), float(node.attr("beta", 1.0))
        c = ctx.constant(node.inputs[2]) if len(node.inputs) > 2 and node.inputs[2] else None
        x, y = ctx.ref(node.inputs[0]), ctx.ref(node.outputs[0])
        if c is None:
            bias = None
        elif c.size == 1:
            bias = ctx.literal(float(c.reshape(-1)[0]))
        else:
            bias = f"{ctx.const(node.inputs[2], c.reshape(-1), f'{node.name} bias [{n}]')}[n]"
        if ctx.quantize:
            return _quantized_lines(node, ctx, w, bias, x, y, n)
        order = _order(ctx, n, (node.inputs[1], w, node.name))
        if alpha == 1.0 and beta == 1.0:
            return _matmul_lines(x, y, wsym, k, n, bias or "0.0f", rows=ctx.rows, order=order)
        lines = _matmul_lines(x, y, wsym, k, n, "0.0f", rows=ctx.rows, order=order)
        scaled = f"{ctx.literal(alpha)} * {y}[n]"
        if bias is not None:
            scaled += f" + {ctx.literal(beta)} * {bias}"
        return [
            *lines,
            *per_row([f"for (uint32_t n = 0u; n < {n}u; ++n) {{", f"    {y}[n] = {scaled};", "}"], ctx.rows),
        ]

    def reference(
        self, node: Node, inputs: Sequence[np.ndarray], constants: Mapping[str, np.ndarray], precision: str
    ) -> np.ndarray:
        trans = bool(node.attr("transB", 0))
        has_c = len(node.inputs) > 2 and bool(node.inputs[2])
        alpha, beta = float(node.attr("alpha", 1.0)), float(node.attr("beta", 1.0))
        if precision == "float64":
            w = constants[node.inputs[1]].astype(np.float64)
            y = alpha * (inputs[0] @ (w.T if trans else w))
            if has_c:
                y = y + beta * constants[node.inputs[2]].astype(np.float64).reshape(-1)
            return np.asarray(y)
        if alpha != 1.0 or beta != 1.0:
            raise UnsupportedOpError(
                f"Gemm node '{node.name}': alpha/beta != 1 are not supported with --quantize"
            )
        b = constants[node.inputs[1]].astype(F)
        w = np.ascontiguousarray(b.T if trans else b)
        c = constants[node.inputs[2]].astype(F).reshape(-1) if has_c else None
        if c is not None and c.size == 1:
            c = np.full(w.shape[1], c[0], F)
        return int8_layer(inputs[0], w, c)


class MatMul(Linear):
    """``Y = A @ B`` with A a runtime [1, K] row (or [K] vector) and B a constant [K, N]."""

    min_inputs = max_inputs = 2

    def shape(self, node: Node, shapes: Mapping[str, Shape], constants: Mapping[str, np.ndarray]) -> Shape:
        a = shapes[node.inputs[0]]
        if not (len(a) == 1 or (len(a) == 2 and a[0] == 1)):
            raise _fail(node, f"A must have shape [K] or [1, K], got {list(a)}")
        if node.inputs[1] not in constants:
            raise _fail(node, f"B '{node.inputs[1]}' must be a constant (weights as initializers)")
        b = constants[node.inputs[1]]
        if b.ndim != 2 or b.shape[0] != a[-1]:
            raise _fail(node, f"B must have shape [{a[-1]}, N], got {list(b.shape)}")
        return (*a[:-1], int(b.shape[1]))

    def affine(self, node: Node, constants: Mapping[str, np.ndarray]) -> Affine:
        return Affine(constants[node.inputs[1]].astype(np.float64).T, None)

    def emit(self, node: Node, ctx: EmitContext, n: int) -> list[str]:
        b = ctx.constant(node.inputs[1])
        assert b is not None
        w = _input_major(node, b, False)
        x, y = ctx.ref(node.inputs[0]), ctx.ref(node.outputs[0])
        if ctx.quantize:
            return _quantized_lines(node, ctx, w, None, x, y, n)
        wsym = ctx.const(
            node.inputs[1] + "#input-major",
            w,
            f"{node.name} weights [{w.shape[0]}][{n}]",
            input_major_condition(ctx.prefix),
        )
        order = _order(ctx, n, (node.inputs[1], w, node.name))
        return _matmul_lines(x, y, wsym, w.shape[0], n, "0.0f", rows=ctx.rows, order=order)

    def reference(
        self, node: Node, inputs: Sequence[np.ndarray], constants: Mapping[str, np.ndarray], precision: str
    ) -> np.ndarray:
        if precision == "float64":
            return np.asarray(inputs[0] @ constants[node.inputs[1]].astype(np.float64))
        return int8_layer(inputs[0], np.ascontiguousarray(constants[node.inputs[1]].astype(F)), None)


INT8_MIN = -128
INT32_MIN, INT32_MAX = -(2**31), 2**31 - 1
SHIFT_RANGE = (-31, 30)
"""Exponents a requantisation multiplier may have (``real = m * 2^(shift - 31)``, ``m`` in [2^30, 2^31)):
below, the multiplier underflows (every output would be the zero point); above, ``acc << shift`` leaves no
bit of the accumulator."""
WORD = 4
"""int8 values per 32-bit word: rows of weights and activation buffers are padded to whole words."""


def quantize_multiplier(real: float) -> tuple[int, int] | None:
    """gemmlowp / TFLite: ``real`` as a Q31 multiplier ``m`` in [2^30, 2^31) and an exponent ``shift``
    (``real ~ m * 2^(shift - 31)``); None if ``real`` is not a positive finite number or its exponent is out
    of :data:`SHIFT_RANGE`."""
    if not (np.isfinite(real) and real > 0):
        return None
    fraction, shift = np.frexp(real)
    m = round(float(fraction) * 2.0**31)
    if m == 2**31:
        m, shift = m // 2, shift + 1
    if not SHIFT_RANGE[0] <= shift <= SHIFT_RANGE[1]:
        return None
    return m, int(shift)


def requantize(acc: np.ndarray, m: np.ndarray, shift: np.ndarray) -> np.ndarray:
    """``acc * m * 2^(shift - 31)`` rounded as gemmlowp does (int64 arrays holding int32 values): a saturating
    left shift for ``shift > 0``, SaturatingRoundingDoublingHighMul (C's division truncates) and
    RoundingDivideByPOT for ``shift < 0``."""
    left = np.maximum(shift, 0)
    x = np.clip(acc << left, INT32_MIN, INT32_MAX)
    ab = x * m
    t = ab + np.where(ab >= 0, np.int64(1) << 30, 1 - (np.int64(1) << 30))
    high = np.where(t >= 0, t >> 31, -((-t) >> 31))
    right = np.maximum(-shift, 0)
    mask = (np.int64(1) << right) - 1
    threshold = (mask >> 1) + (high < 0)
    return np.asarray((high >> right) + ((high & mask) > threshold), dtype=np.int64)


REQUANT_CLAMP = 256
"""The general requantisation returns its result clamped to [-256, 255]: adding a zero point in [-128, 127]
cannot overflow, and the final clamp to int8 gives what the unclamped value would."""


def requantize_source(prefix: str) -> str:
    """The C of :func:`requantize`, then the output zero point and the clamp (int32 in, int8 out): every
    piece below, in order (``{prefix}_requantize`` takes any shift)."""
    return "\n\n".join(piece(prefix) for piece in (clamp_source, right_source, general_source))


def clamp_source(prefix: str) -> str:
    """The output zero point and the clamp to int8 (the ReLU's lower end)."""
    return f"""/* The output zero point added to a requantised r, clamped to [low, 127] (low above -128: the
 * ReLU). */
static inline int8_t {prefix}_clamp(int32_t r, int32_t zero, int32_t low)
{{
    int32_t q = r + zero;
    q = (q > {INT8_MAX}) ? {INT8_MAX} : q;
    q = (q < low) ? low : q; /* two conditional moves, no branch */
    return (int8_t)q;
}}"""


def right_source(prefix: str) -> str:
    """The requantisation for shift < 0, branch-free (with the zero point and the clamp)."""
    return f"""/* acc * m * 2^(shift - 31) rounded as gemmlowp, for shift < 0: both roundings in one 64-bit
 * sum. With c = 1 if acc < 0 (then gemmlowp's high is negative, or 0 whatever the rounding), the result is
 * floor((acc m + 2^30 - c 2^31 + 2^(30 - shift)) / 2^(31 - shift)), taken as u = acc m + (c ? -2^30 :
 * 2^30), w = floor(u / 2^31) (fits an int32), then ((w >> (-shift - 1)) + 1) >> 1; then the zero point and
 * the clamp. No branch: a layer whose shifts are all negative calls it directly, and a compiler may
 * vectorise a loop of it. */
static inline int8_t {prefix}_requantize_right(int32_t acc, int32_t m, int32_t shift, int32_t zero,
                                               int32_t low)
{{
    /* -2^30 if acc < 0, else 2^30: its high word is acc's sign, its low word acc's bit 31 and 2^30 */
    const uint32_t low_word = ((uint32_t)acc & 0x80000000u) | 0x40000000u;
    const int64_t nudge = (int64_t)(acc >> 31) * ((int64_t)1 << 32) + (int64_t)low_word;
    const int32_t w = (int32_t)(((int64_t)acc * (int64_t)m + nudge) >> 31);
    return {prefix}_clamp(((w >> (-shift - 1)) + 1) >> 1, zero, low);
}}"""


def general_source(prefix: str) -> str:
    """gemmlowp's steps for any shift, and ``{prefix}_requantize`` choosing between the two forms: emitted
    only for a layer with a shift >= 0."""
    return f"""/* acc * m * 2^(shift - 31) rounded as gemmlowp (m within [2^30, 2^31), shift within
 * [-31, 30]), operation by operation: saturating left shift for shift > 0, SaturatingRoundingDoublingHighMul
 * (m > 0: it never saturates; gemmlowp's nudge and truncating division are (x m + 2^30) >> 31 rounding down),
 * RoundingDivideByPOT by -shift. Used for shift >= 0 (a scale of 1/2 or more: rare); its result is clamped to
 * [-{REQUANT_CLAMP}, {REQUANT_CLAMP - 1}], which the int8 clamp after the zero point cannot tell apart. */
#if defined(__GNUC__)
__attribute__((cold, noinline))
#endif
static int32_t {prefix}_requantize_general(int32_t acc, int32_t m, int32_t shift)
{{
    int64_t x = acc;
    if (shift > 0) {{
        x = x * ((int64_t)1 << shift);
        x = (x > INT32_MAX) ? INT32_MAX : ((x < INT32_MIN) ? INT32_MIN : x);
    }}
    const int32_t high = (int32_t)((x * (int64_t)m + ((int64_t)1 << 30)) >> 31);
    const int32_t right = (shift > 0) ? 0 : -shift;
    const int32_t mask = (int32_t)((1u << (uint32_t)right) - 1u);
    const int32_t threshold = (mask >> 1) + (high < 0 ? 1 : 0);
    const int32_t r = (high >> right) + ((high & mask) > threshold ? 1 : 0);
    return (r > {REQUANT_CLAMP - 1}) ? {REQUANT_CLAMP - 1} : ((r < -{REQUANT_CLAMP}) ? -{REQUANT_CLAMP} : r);
}}

/* Any shift: the branch-free form for shift < 0, the general one otherwise. */
static inline int8_t {prefix}_requantize(int32_t acc, int32_t m, int32_t shift, int32_t zero, int32_t low)
{{
    return (shift < 0) ? {prefix}_requantize_right(acc, m, shift, zero, low)
                     : {prefix}_clamp({prefix}_requantize_general(acc, m, shift), zero, low);
}}"""


def requantize16(acc: np.ndarray, m: np.ndarray, shift: np.ndarray) -> np.ndarray:
    """The last layer's sums as the int16 input of tanh or sigmoid (:mod:`embedrl.export.ops.squash`):
    ``acc * m * 2^(shift - 31)`` rounded once, half up, from the exact 64-bit product (one rounding where
    gemmlowp's :func:`requantize` has two), clamped to int16 (int64 arrays)."""
    s = 31 - shift
    r = (acc * m + (np.int64(1) << (s - 1))) >> s
    return np.asarray(np.clip(r, INT16_MIN, INT16_MAX), np.int64)


def requantize16_source(prefix: str) -> str:
    """The C of :func:`requantize16`: the floor taken on the product plus 2^62 (never negative), so that
    every shift is of an unsigned value (MISRA C:2012 rule 10.1)."""
    offset = 1 << 62
    return f"""/* acc * m * 2^(shift - 31) (m within [2^30, 2^31), shift within [-31, 30]) rounded half up
 * from the 64-bit product, clamped to int16: the int16 input of tanh or sigmoid. The floor by
 * 2^(31 - shift) is taken on the product plus 2^62 + half (never negative, below 2^63), less 2^62's share. */
static int32_t {prefix}_requantize16(int32_t acc, int32_t m, int32_t shift)
{{
    const int32_t total = 31 - shift;
    const uint32_t s = (uint32_t)total;
    const int64_t product = (int64_t)acc * (int64_t)m;
    const uint64_t half = ((uint64_t)1u << s) >> 1u;
    const uint64_t biased = ((uint64_t)product + {offset:#x}u) + half;
    const uint64_t shifted = biased >> s;
    const uint64_t base = (uint64_t){offset:#x}u >> s;
    const int64_t r = (int64_t)shifted - (int64_t)base;
    return (int32_t)((r > {INT16_MAX}) ? {INT16_MAX} : ((r < {INT16_MIN}) ? {INT16_MIN} : r));
}}"""


def host_condition(prefix: str) -> str:
    """When the host loop is compiled: x86-64, and no -D<PREFIX>_PORTABLE."""
    return f"defined(__x86_64__) && !defined({prefix.upper()}_PORTABLE)"


def dsp_condition(prefix: str) -> str:
    """When the DSP loop is compiled: the core has the ACLE SIMD32 intrinsics, and no -D<PREFIX>_PORTABLE."""
    return (
        f"defined(__ARM_FEATURE_DSP) && defined(__ARM_FEATURE_SIMD32) && !defined({prefix.upper()}_PORTABLE)"
    )


def byte_source(prefix: str) -> str:
    """Portable loop: int8 value ``j`` (0-3, least significant first) of a packed weight word."""
    return f"""#if !({host_condition(prefix)})
static inline int32_t {prefix}_byte(uint32_t u, uint32_t j)
{{
    return (int32_t)(((u >> (8u * j)) & 0xFFu) ^ 0x80u) - 128;
}}
#endif"""


def odd_source(prefix: str) -> str:
    """DSP inner loop: bytes 1 and 3 of a word sign-extended into two int16 (``__sxtb16`` of the word rotated
    by 8; ACLE has no rotated form, so gcc gets SXTB16's ``ROR #8`` operand written out). ``r`` starts as
    ``w``, a store the compiler drops, so that cppcheck (which does not read assembly operands) sees the
    parameter used (MISRA C:2012 rule 2.7)."""
    return f"""#if {prefix.upper()}_DSP
static inline int32_t {prefix}_odd(int32_t w)
{{
#if defined(__GNUC__)
    int32_t r = w; /* overwritten by the assembly; w here for cppcheck, which skips assembly operands */
    __asm__("sxtb16 %0, %1, ror #8" : "=r"(r) : "r"(w));
    return r;
#else
    const uint32_t u = (uint32_t)w;
    return __sxtb16((int32_t)((u >> 8) | (u << 24)));
#endif
}}
#endif"""


def bias_type(bias: np.ndarray) -> type[np.signedinteger]:
    """int16 for a layer whose every bias fits (half the flash, the same one load per output), else int32."""
    fits = bool(np.all((bias >= INT16_MIN) & (bias <= INT16_MAX)))
    return np.int16 if fits else np.int32


def padded(k: int) -> int:
    """``k`` rounded up to whole :data:`WORD` s."""
    return -(-k // WORD) * WORD


ROWS_PER_PASS = 4
"""Outputs summed in one pass over the input (CMSIS-NN's 4-row kernel): each pair of input words is loaded
once for four rows of weights. Outputs left over go in a pass of two, then of one."""


@dataclass(frozen=True)
class RowBlocks:
    """A run of blocks of ``rows`` outputs each, from output ``first``; their weights start at word
    ``offset`` of the layer's packed array, ``words`` words a block."""

    first: int
    rows: int
    count: int
    offset: int
    words: int


def tail_inputs(k: int) -> int:
    """A row's last inputs kept in tail words (:func:`pack_weights`) instead of a word half or more padding:
    ``k % 4`` when that is 1 or 2, else 0 (a tail of three takes a padded word)."""
    return k % WORD if k % WORD in (1, 2) else 0


def word_groups(k: int) -> int:
    """Groups of four inputs a row keeps in whole words: all but its tail."""
    return padded(k - tail_inputs(k)) // WORD


def tail_words(rows: int, k: int) -> int:
    """Tail words of a block of ``rows`` outputs: one per two rows (none without a tail)."""
    return -(-rows // 2) if tail_inputs(k) else 0


def row_blocks(n_out: int, k: int) -> list[RowBlocks]:
    """The layer's outputs in passes of :data:`ROWS_PER_PASS`, then 2, then 1 (as many as needed), with
    where each run's weights start in the packed array of a layer of ``k`` inputs."""
    runs, first, offset = [], 0, 0
    for rows in (ROWS_PER_PASS, 2, 1):
        count = (n_out - first) // rows
        if count:
            words = rows * word_groups(k) + tail_words(rows, k)
            runs.append(RowBlocks(first, rows, count, offset, words))
            first, offset = first + rows * count, offset + words * count
    return runs


def pack_weights(weights: np.ndarray) -> np.ndarray:
    """int8 [N][K] -> int32 words in the order the kernels read them: per block of rows (:func:`row_blocks`),
    per group of four inputs, the block's rows one word each; a word holds inputs ``4g .. 4g + 3`` of one row,
    the first in its least significant byte; the padding to whole words is zero. A tail of one or two inputs
    (:func:`tail_inputs`, from input ``4G``) follows a block's groups, two rows to a word: bytes
    ``w0[4G], w1[4G], w0[4G + 1], w1[4G + 1]`` (0 where there is no row or input), which ``__sxtb16`` splits
    into each row's pair for the input pair ``(x[4G], x[4G + 1])``."""
    n_out, k_in = weights.shape
    groups, tail = word_groups(k_in), tail_inputs(k_in)
    rows = np.zeros((n_out, WORD * groups), np.int8)
    rows[:, : min(k_in, WORD * groups)] = weights[:, : WORD * groups]
    words = rows.view("<i4")  # [N][groups], little-endian: byte j of the word is input 4g + j
    lanes = np.zeros((n_out + 1, 2), np.int8)  # one row more: an odd block's missing row is 0
    lanes[:n_out, :tail] = weights[:, WORD * groups :]
    blocks = []
    for run in row_blocks(n_out, k_in):
        for b in range(run.count):
            first = run.first + b * run.rows
            blocks.append(words[first : first + run.rows].T.reshape(-1))
            for pair in range(tail_words(run.rows, k_in)):
                r0 = first + 2 * pair
                r1 = r0 + 1 if 2 * pair + 1 < run.rows else n_out
                tail_bytes = np.array([lanes[r0, 0], lanes[r1, 0], lanes[r0, 1], lanes[r1, 1]], np.int8)
                blocks.append(tail_bytes.view("<i4"))
    return np.concatenate([*blocks, np.zeros(0, np.int32)]).astype(np.int32)


@dataclass(frozen=True)
class Int8Layer:
    """One Gemm or MatMul in full-integer int8 (planned by :func:`embedrl.export.full_integer.plan`): int8
    inputs with a zero point, per-channel symmetric int8 weights, int32 sums from the bias, then a gemmlowp
    requantisation and a clamp that holds the ReLU; the last layer turns its sums into float instead, or,
    with a ``squash``, requantises them to int16 for the int16 tanh or sigmoid (:mod:`.squash`). Its
    integer model (:meth:`reference`) and its C (:meth:`c_lines`) are the same arithmetic bit for bit."""

    name: str
    weights: np.ndarray
    """int8 [N][K], output-major."""
    bias: np.ndarray
    """int64 [N] holding int32, in accumulator units (input scale x channel weight scale), with the input's
    zero point folded in: ``round(b / (s_in s_w)) - zp_in * sum_k w[n][k]``."""
    multiplier: np.ndarray
    """int64 [N], Q31 multipliers of ``s_in s_w[n] / s_out`` (hidden layers; with a squash, ``s_out`` the
    int16 input's step): in [2^30, 2^31) each with its own shift, or, where the layer's channels share one
    shift, in [2^23, 2^31) (:func:`embedrl.export.full_integer.common_shift`)."""
    shift: np.ndarray
    """int64 [N], their exponents (see :func:`requantize`)."""
    out_zero: int
    """Zero point of the int8 output (hidden layers)."""
    relu: bool
    out_scale: np.ndarray | None
    """float32 [N] ``s_in s_w[n]`` for a last layer whose float output is its sums; None otherwise."""
    squash: str | None = None
    """A last layer's output non-linearity in int16 ("Tanh" or "Sigmoid"), or None."""

    def reference(self, q: np.ndarray) -> np.ndarray:
        """The layer on a batch of int8 inputs (as int64): int8 outputs (as int64), or float32 if last."""
        acc = q @ self.weights.astype(np.int64).T + self.bias
        if self.squash is not None:
            t = requantize16(acc, self.multiplier, self.shift)
            return squash_model(t, self.squash)
        if self.out_scale is not None:
            return np.asarray(acc.astype(F) * self.out_scale, dtype=F)
        r = requantize(acc, self.multiplier, self.shift) + self.out_zero
        return np.asarray(np.clip(r, self.out_zero if self.relu else INT8_MIN, INT8_MAX))

    def c_lines(self, ctx: EmitContext, src: str, dst: str, scratch: tuple[str, str, str]) -> list[str]:
        """C reading the int8 array ``src`` (padded to whole words) and writing ``dst`` (int8, or the float
        output if last); ``scratch`` names the DSP loop's int16 pairs, the host loop's int16 input and its
        int32 sums. DSP (Cortex-M4/M7): packed weight words (:func:`pack_weights`), the input unpacked once
        into ``pairs`` (per word: its even bytes, then its odd bytes, as int16 pairs, ``__sxtb16``), then
        four outputs per pass sharing each load of the input, each weight word two ``__sxtb16`` and two
        ``__smlad`` (four multiply-adds); each output requantised once, when its sum is complete. x86-64:
        :func:`_host_lines`, over int16 rows of its own. Every other core: a dot product per output over the
        packed words. Each build compiles only its own weight array."""
        pairs, wide, sums = scratch
        n_out, k_in = self.weights.shape
        groups = word_groups(k_in)
        host = host_condition(ctx.prefix)
        w = ctx.const(
            f"{self.name}#int8full",
            pack_weights(self.weights),
            f"{self.name} weights, int8 [{n_out}][{k_in}] packed four to a word, {ROWS_PER_PASS} rows "
            f"interleaved per group of four inputs"
            + (f", then inputs {WORD * groups}.. of two rows a word" if tail_inputs(k_in) else ""),
            f"!({host})",
        )
        tail = Tail(WORD * groups, tail_inputs(k_in)) if tail_inputs(k_in) else None
        wide_rows = np.zeros((n_out, host_row(k_in)), np.int16)
        wide_rows[:, :k_in] = self.weights
        host_w = ctx.const(
            f"{self.name}#int16rows",
            wide_rows,
            f"{self.name} weights, int8 values as int16 [{n_out}][{k_in}], a row per output padded to "
            f"{host_row(k_in)} with 0",
            host,
        )
        b = ctx.const(
            f"{self.name}#int8bias",
            self.bias.astype(bias_type(self.bias)),
            f"{self.name} bias in accumulator units",
        )
        finish = self._finish(ctx, dst)
        up = ctx.prefix.upper()
        odd, barrier = ctx.function("odd", odd_source), ctx.function("barrier", barrier_source)
        lines = [
            f"/* {self.name}: [{k_in}] -> [{n_out}]{' + ReLU' if self.relu else ''}, int8 x int8 -> int32 */",
            f"#if {up}_DSP",
            f"for (uint32_t g = 0u; g < {padded(k_in) // WORD}u; ++g) {{",
            f"    const uint8_t *bytes = (const uint8_t *)&{src}[{WORD}u * g];",
            "    /* four inputs, least significant first as the weights are packed: gcc loads one word */",
            "    const uint32_t u = (uint32_t)bytes[0] | ((uint32_t)bytes[1] << 8u)",
            "                       | ((uint32_t)bytes[2] << 16u) | ((uint32_t)bytes[3] << 24u);",
            f"    {pairs}[2u * g] = __sxtb16((int32_t)u);",
            f"    {pairs}[(2u * g) + 1u] = {odd}((int32_t)u);",
            "}",
        ]
        if tail is not None:  # the input pair (x[4G], x[4G + 1]) of the tail, from the unpacked pairs
            g = tail.first // WORD
            lines += [
                "{",
                f"const uint32_t low = (uint32_t){pairs}[{2 * g}u] & 0xFFFFu;",
                f"const uint32_t high = (uint32_t){pairs}[{2 * g + 1}u] << 16u;",
                "const uint32_t both = low | high;",
                "const int32_t tail_pair = (int32_t)both; /* a plain value cast (10.8): the same code */",
            ]
        for run in row_blocks(n_out, k_in):
            lines += _dsp_pass(run, (groups, tail), w, b, pairs, (odd, barrier), finish)
        lines += ["}"] if tail is not None else []
        lines += [
            f"#elif {host}",
            *_host_lines(src, (wide, host_w, b, sums), self.weights.shape, finish),
            "#else",
        ]
        byte = ctx.function("byte", byte_source)
        for run in row_blocks(n_out, k_in):
            lines += _portable_pass(run, (groups, tail), w, b, src, byte, finish)
        return [*lines, "#endif"]

    def _finish(self, ctx: EmitContext, dst: str) -> str:
        """The statement storing output ``n`` from its sum ``acc`` (a format string of ``acc`` and ``n``): a
        layer whose shifts are all negative (the usual case) calls the branch-free requantisation, which
        the portable loop's pass over the sums lets a compiler vectorise."""
        n_out = self.weights.shape[0]
        if self.squash is not None:
            ctx.function("tanh_q15", tanh_source)
            requant16 = ctx.function("requantize16", requantize16_source)
            m = ctx.const(
                f"{self.name}#int8mult", self.multiplier.astype(np.int32), f"{self.name} multipliers"
            )
            sh = ctx.const(f"{self.name}#int8shift", self.shift.astype(np.int8), f"{self.name} shifts")
            t = f"{requant16}({{acc}}, {m}[{{n}}], {sh}[{{n}}])"
            return f"{dst}[{{n}}] = {squash_c(ctx.prefix, self.squash, t)};"
        if self.out_scale is not None:
            s = ctx.const(f"{self.name}#int8scale", self.out_scale, f"{self.name} output scales [{n_out}]")
            return f"{dst}[{{n}}] = (float){{acc}} * {s}[{{n}}];"
        ctx.function("clamp", clamp_source)
        requant = ctx.function("requantize_right", right_source)
        if not bool(np.all(self.shift < 0)):
            requant = ctx.function("requantize", general_source)
        m = ctx.const(f"{self.name}#int8mult", self.multiplier.astype(np.int32), f"{self.name} multipliers")
        if bool(np.all(self.shift == self.shift[0])):  # one shift for the layer: a constant, no table
            shift = str(int(self.shift[0]))
        else:
            sh = ctx.const(f"{self.name}#int8shift", self.shift.astype(np.int8), f"{self.name} shifts")
            shift = f"{sh}[{{n}}]"
        low = self.out_zero if self.relu else INT8_MIN
        return f"{dst}[{{n}}] = {requant}({{acc}}, {m}[{{n}}], {shift}, {self.out_zero}, {low});"


def _index(*terms: str) -> str:
    """A C sum of the terms that are not empty or "0" (no ``+ 0``: MISRA 2.2), its integer literals unsigned
    as the loop counters they combine with (MISRA 10.4: no signed and unsigned operands in one operation)."""
    kept = [_UNSIGNED_LITERAL.sub(r"\1u", t) for t in terms if t not in ("", "0")]
    total = " + ".join(kept)
    if " + " in total:  # the products of a sum in parentheses (MISRA 12.1)
        total = _PRODUCT.sub(r"(\1)", total)
    return total or "0u"


_UNSIGNED_LITERAL = re.compile(r"\b(\d+)\b(?!u)")
_PRODUCT = re.compile(r"\b(\w+ \* \w+)\b")


def _block(run: RowBlocks) -> str:
    """The first output of block ``b`` of the run, as C."""
    return _index(str(run.first), f"{run.rows} * b" if run.count > 1 else "")


GROUPS_PER_ITERATION = (4, 5, 3)
"""Groups of four inputs per iteration of the DSP loop: the first of these that divides the layer's groups
(no groups left after the loop), else the first, the rest unrolled after the loop. Measured on the study's
actor (Cortex-M4 cycle model): 25 groups per row, 1 per iteration 28.4k cycles, 2: 26.0k, 4: 24.9k, 5: 24.1k.
A compiler barrier between groups keeps each group's loads after the previous group's sums (without it gcc 12
loads all the groups' words first and spills accumulators to the stack)."""


def _groups_per_iteration(groups: int) -> int:
    """See :data:`GROUPS_PER_ITERATION`."""
    return next((g for g in GROUPS_PER_ITERATION if groups % g == 0), GROUPS_PER_ITERATION[0])


def barrier_source(prefix: str) -> str:
    """DSP loop: an empty statement the compiler may not move memory accesses across (GNU C)."""
    return f"""#if {prefix.upper()}_DSP
static inline void {prefix}_barrier(void)
{{
#if defined(__GNUC__)
    __asm__ volatile("" : : : "memory");
#endif
}}
#endif"""


def _dsp_group(rows: int, g: str, j: int, pairs: str, odd: str) -> list[str]:
    """The group ``g + j`` of four inputs (``g`` the loop's C variable, or "" for the constant group ``j``)
    for ``rows`` sums ``a0..``: ``2 * rows`` SMLAD."""

    def at(scale: int, plus: int) -> str:
        return _index(f"{scale} * {g}" if g else "", str(scale * j + plus))

    lines = [
        "{",
        f"    const int32_t e = {pairs}[{at(2, 0)}];",
        f"    const int32_t o = {pairs}[{at(2, 1)}];",
    ]
    lines += [f"    const int32_t w{i} = w[{at(rows, i)}];" for i in range(rows)]
    for i in range(rows):
        lines += [
            f"    a{i} = __smlad(e, __sxtb16(w{i}), a{i});",
            f"    a{i} = __smlad(o, {odd}(w{i}), a{i});",
        ]
    return [*lines, "}"]


@dataclass(frozen=True)
class Tail:
    """A layer's last one or two inputs, their weights in tail words (:func:`pack_weights`)."""

    first: int
    """The first of these inputs (``4G``)."""
    inputs: int


def _dsp_tail(r: int, groups: int, odd: str) -> list[str]:
    """The tail's multiply-adds for the pass's ``r`` sums: per two rows one word, one SMLAD a row against
    ``tail_pair``, the input pair ``(x[4G], x[4G + 1])``."""
    lines = []
    for j in range(-(-r // 2)):
        lines.append(f"const int32_t t{j} = w[{r * groups + j}u];")
        lines.append(f"a{2 * j} = __smlad(tail_pair, __sxtb16(t{j}), a{2 * j});")
        if 2 * j + 1 < r:
            lines.append(f"a{2 * j + 1} = __smlad(tail_pair, {odd}(t{j}), a{2 * j + 1});")
    return ["{", *(f"    {line}" for line in lines), "}"]


def _dsp_pass(
    run: RowBlocks,
    layout: tuple[int, Tail | None],
    w: str,
    b: str,
    pairs: str,
    fns: tuple[str, str],
    finish: str,
) -> list[str]:
    """The DSP kernel over one run of blocks: ``run.rows`` sums per pass, each input word pair loaded once
    (``layout``: the groups in words and the tail; ``fns``: the odd-bytes and barrier functions). Passes of
    four rows run several groups per iteration (:data:`GROUPS_PER_ITERATION`), the few others one."""
    (groups, tail), (odd, barrier), r = layout, fns, run.rows
    step = _groups_per_iteration(groups) if r == ROWS_PER_PASS else 1
    whole = groups - groups % step
    body = [f"{barrier}();" if j else "" for j in range(step)]
    lines = [
        f"for (uint32_t b = 0u; b < {run.count}u; ++b) {{ /* {r} output(s) per pass, {4 * r} multiply-adds "
        f"per group of four inputs in {2 * r} SMLAD */",
        f"    const int32_t *w = &{w}[{_index(str(run.offset), f'{run.words} * b')}];",
        *(f"    int32_t a{i} = {b}[{_index(_block(run), str(i))}];" for i in range(r)),
    ]
    if whole:
        lines += [f"    for (uint32_t g = 0u; g < {whole}u; g += {step}u) {{"]
        for j in range(step):
            lines += [
                f"        {line}"
                for line in ([body[j]] if body[j] else []) + _dsp_group(r, "g", j, pairs, odd)
            ]
        lines.append("    }")
    for g in range(whole, groups):
        lines += [f"    {line}" for line in _dsp_group(r, "", g, pairs, odd)]
    if tail is not None:
        lines += [f"    {line}" for line in _dsp_tail(r, groups, odd)]
    lines += [f"    {finish.format(acc=f'a{i}', n=_index(_block(run), str(i)))}" for i in range(r)]
    return [*lines, "}"]


HOST_ROWS = 8
"""Outputs the host loop sums in one pass over the input (each input vector loaded once for all of them)."""
HOST_LANES = 16
"""int16 values in an AVX2 vector: the host loop's rows of weights are padded to whole vectors."""


def host_row(k: int) -> int:
    """The host loop's row length for ``k`` inputs: whole :data:`HOST_LANES` vectors."""
    return -(-k // HOST_LANES) * HOST_LANES


def _host_lines(
    src: str, arrays: tuple[str, str, str, str], shape: tuple[int, ...], finish: str
) -> list[str]:
    """The host loop (x86-64; ``arrays``: the int16 input, the int16 weights [N][K padded], the biases, the
    int32 sums): ``src`` widened to int16 once, :data:`HOST_ROWS` outputs summed per pass over whole
    vectors of the input (the padding's weights are 0), the rest one per pass, then every output from its
    sum in a pass of its own. gcc vectorises the sums (``pmaddwd``, 8 multiply-adds per SSE2 instruction,
    16 per AVX2 one) and, under AVX2, the requantisation."""
    wide, rows, b, sums = arrays
    n_out, k_in = shape
    row, whole = host_row(k_in), n_out - n_out % HOST_ROWS
    at = [_index("n", f"{i}u" if i else "") for i in range(HOST_ROWS)]
    lines = [
        f"for (uint32_t k = 0u; k < {k_in}u; ++k) {{",
        f"    {wide}[k] = (int16_t){src}[k];",
        "}",
    ]
    if whole:
        lines += [
            f"for (uint32_t n = 0u; n < {whole}u; n += {HOST_ROWS}u) {{",
            *(f"    int32_t a{i} = {b}[{at[i]}];" for i in range(HOST_ROWS)),
            f"    for (uint32_t k = 0u; k < {row}u; ++k) {{",
            f"        const int32_t v = (int32_t){wide}[k];",
            *(f"        a{i} += v * (int32_t){rows}[{at[i]}][k];" for i in range(HOST_ROWS)),
            "    }",
            *(f"    {sums}[{at[i]}] = a{i};" for i in range(HOST_ROWS)),
            "}",
        ]
    if whole < n_out:
        lines += [
            f"for (uint32_t n = {whole}u; n < {n_out}u; ++n) {{",
            f"    int32_t a0 = {b}[n];",
            f"    for (uint32_t k = 0u; k < {row}u; ++k) {{",
            f"        a0 += (int32_t){wide}[k] * (int32_t){rows}[n][k];",
            "    }",
            f"    {sums}[n] = a0;",
            "}",
        ]
    return [
        *lines,
        f"for (uint32_t n = 0u; n < {n_out}u; ++n) {{",
        f"    {finish.format(acc=f'{sums}[n]', n='n')}",
        "}",
    ]


def _portable_pass(
    run: RowBlocks, layout: tuple[int, Tail | None], w: str, b: str, src: str, byte: str, finish: str
) -> list[str]:
    """The portable loop over one run of blocks: a dot product per output, reading its packed words, then
    its bytes of the block's tail words."""
    (groups, tail), r = layout, run.rows
    n = _index(_block(run), "i")
    word = _index(str(run.offset), f"{run.words} * b", f"{r} * g + i" if r > 1 else "g")
    words = [
        f"        for (uint32_t g = 0u; g < {groups}u; ++g) {{",
        f"            const uint32_t u = (uint32_t){w}[{word}];",
        *(f"            acc += (int32_t){src}[{_index(f'{WORD} * g', str(j))}] * {byte}(u, {j}u);"
          for j in range(WORD)),
        "        }",
    ] if groups else []  # fmt: skip
    if tail is not None:  # row i's bytes of its tail word: i % 2, then 2 + i % 2
        at = _index(str(run.offset), f"{run.words} * b", str(r * groups), "(i >> 1u)" if r > 1 else "")
        lane = "(i & 1u)" if r > 1 else ""
        words += [
            f"        const uint32_t h = (uint32_t){w}[{at}];",
            *(f"        acc += (int32_t){src}[{tail.first + j}u] * {byte}(h, {_index(str(2 * j), lane)});"
              for j in range(tail.inputs)),
        ]  # fmt: skip
    return [
        f"for (uint32_t b = 0u; b < {run.count}u; ++b) {{",
        f"    for (uint32_t i = 0u; i < {r}u; ++i) {{",
        f"        int32_t acc = {b}[{n}];",
        *words,
        f"        {finish.format(acc='acc', n=n)}",
        "    }",
        "}",
    ]
