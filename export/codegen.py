"""IR -> C99: a pure function, graph in, ``{filename: text}`` out. Only the CLI writes files.

The generated code has no malloc and no stdio; it needs ``<math.h>`` (link with ``-lm``).
Weights are ``static const`` arrays whose literals round-trip exactly. Intermediate values live
in file-scope ``static float`` buffers, reused across layers by a liveness plan: the RAM is the
sum of those buffers, printed in the header. ``<name>_step`` is therefore not reentrant: one
call at a time per policy (two policies with different names have separate buffers).
Output is deterministic: no timestamps; provenance is hashes and the tool version.
"""

from __future__ import annotations

import re
from collections.abc import Callable, Mapping, Sequence
from dataclasses import dataclass, field
from string import Template

import numpy as np

from embedrl.escape import COMMENT_LIMIT, c_comment, identifier
from embedrl.export.contract.literals import c_float
from embedrl.export.errors import ExportError
from embedrl.export.interpret import Section
from embedrl.export.ir import Graph
from embedrl.export.ops import EMITTERS
from embedrl.export.ops.deterministic import helper_source
from embedrl.export.ops.linear import per_row
from embedrl.train.interface import Interface

NAME_PATTERN = re.compile(r"[a-z][a-z0-9_]{0,30}")
"""Allowed ``--name``: a lower-case C identifier, so the prefix is valid in every symbol (no leading
underscore: such identifiers are reserved)."""
C_KEYWORDS = (
    "auto break case char const continue default do double else enum extern float for goto if inline int "
    "long register restrict return short signed sizeof static struct switch typedef union unsigned void "
    "volatile while bool true false"
)
STANDARD_HEADERS = (
    "assert complex ctype errno fenv inttypes iso646 limits locale math setjmp signal stdarg stdbool stddef "
    "stdint stdio stdlib string tgmath time wchar wctype"
)
"""A generated ``name.h`` beside the sources would shadow ``<name.h>``."""
RUNTIME_FILES = "node e2e platform policy_io policy_dbc main startup"
"""The C runtime's own files, compiled beside the policy."""
RESERVED_NAMES = frozenset(f"{C_KEYWORDS} {STANDARD_HEADERS} {RUNTIME_FILES}".split())
"""Names a generated ``{name}.h``/``{name}_step`` would collide with."""


HOST_STEM = "_host"
"""``{name}_host.c`` and ``{name}_host.h``: the batch entry point, built only into the host's programs."""
HOST_SUFFIX = f"{HOST_STEM}.c"
BATCH_ROWS = 8
"""Observations ``{name}_step_batch`` runs through the network together."""
TARGET_CLONES = ("default", "avx2")
"""Instruction sets the x86-64 step is compiled for (``target_clones``): the baseline and AVX2, neither with
fused multiply-add in gcc (AVX-512 always brings it, and gcc 12's vectoriser then fuses lanes that alternate
add and subtract into ``vfmaddsub`` even under ``-ffp-contract=off``, which changes the bits)."""


def check_name(name: str) -> None:
    """A clear error unless ``name`` can prefix every generated symbol and file."""
    if not NAME_PATTERN.fullmatch(name):
        raise ExportError(
            f"--name {name!r} is not valid: use a lower-case C identifier (a-z first, then a-z, 0-9, _; "
            "at most 31 characters)"
        )
    if name in RESERVED_NAMES:
        raise ExportError(
            f"--name {name!r} is reserved (a C keyword, a standard header or a runtime file); choose another"
        )


VALUES_PER_LINE = 6
PROVENANCE_LIMIT = 240
"""Characters of one provenance line (a file name and a SHA-256 fit)."""
_INTEGER_CTYPES = {
    "int8": "int8_t",
    "uint8": "uint8_t",
    "int16": "int16_t",
    "uint16": "uint16_t",
    "int32": "int32_t",
    "int64": "int64_t",
}


def const_comment(key: str, comment: str) -> str:
    """The comment above a constant array: its key's identifier first (what the deployment report's layer
    table attributes the array by), then the op's description; both from safe text only."""
    return f"/* {identifier(key.split('#')[0])}: {c_comment(comment, COMMENT_LIMIT * 2)} */"


@dataclass
class _Plan:
    """Where every runtime value lives: the input parameter or a scratch buffer index."""

    storage: dict[str, str] = field(default_factory=dict)
    buffer_sizes: list[int] = field(default_factory=list)


def plan_buffers(graph: Graph, input_ref: str, skip: frozenset[str] = frozenset()) -> _Plan:
    """Assign scratch buffers by liveness; element-wise ops run in place when their input dies.

    Nodes named in ``skip`` are computed elsewhere (a fixed-point section) and get no float buffer.
    """
    last_use: dict[str, int] = {}
    for index, node in enumerate(graph.nodes):
        for i in node.inputs:
            if i and not graph.is_constant(i):
                last_use[i] = index
    last_use[graph.output] = len(graph.nodes)
    plan = _Plan()
    plan.storage[graph.input] = input_ref
    storage_end: dict[str, int] = {input_ref: len(graph.nodes) + 1}  # the input is never overwritten
    for k, (read, write) in enumerate(graph.states):
        plan.storage[read] = f"state{k}"  # the module's static state: read all step, written after it
        storage_end[f"state{k}"] = len(graph.nodes) + 1
        last_use[write] = len(graph.nodes)
    fixed = {input_ref, "fixed", *(f"state{k}" for k in range(len(graph.states)))}
    free: list[str] = []

    def end(value: str) -> int:
        return last_use.get(value, -1)

    for index, node in enumerate(graph.nodes):
        emitter = EMITTERS[node.op]
        out = node.outputs[0]
        src = plan.storage.get(node.inputs[0], "")
        if node.name in skip:
            plan.storage[out] = "fixed"
            storage_end["fixed"] = len(graph.nodes) + 1
            continue
        if len(node.outputs) > 1:
            for extra in node.outputs[1:]:
                if extra:
                    buf = free.pop(0) if free else str(len(plan.buffer_sizes))
                    if buf == str(len(plan.buffer_sizes)):
                        plan.buffer_sizes.append(0)
                    plan.storage[extra] = buf
                    storage_end[buf] = end(extra)
                    plan.buffer_sizes[int(buf)] = max(plan.buffer_sizes[int(buf)], graph.size(extra))
        if emitter.alias:
            plan.storage[out] = src
            storage_end[src] = max(storage_end[src], end(out))
        elif emitter.in_place and src not in fixed and storage_end.get(src, -1) == index:
            plan.storage[out] = src
            storage_end[src] = end(out)
        else:
            if free:
                buf = free.pop(0)
            else:
                buf = str(len(plan.buffer_sizes))
                plan.buffer_sizes.append(0)
            plan.storage[out] = buf
            storage_end[buf] = end(out)
        buf = plan.storage[out]
        if buf not in fixed:
            plan.buffer_sizes[int(buf)] = max(plan.buffer_sizes[int(buf)], graph.size(out))
        for s, e in list(storage_end.items()):
            if e == index and s not in fixed and s not in free:
                free.append(s)
                free.sort(key=int)
    return plan


class _Context:
    """The :class:`export.ops.EmitContext` the emitters write through."""

    def __init__(self, graph: Graph, prefix: str, plan: _Plan, quantize: str | None = None) -> None:
        self.graph, self.prefix, self.plan = graph, prefix, plan
        self.quantize = quantize
        self.rows: str | None = None
        """Set while the block of rows is emitted (see :attr:`export.ops.EmitContext.rows`)."""
        self.helpers: dict[str, str] = {}
        """Deterministic math helpers emitted so far: name -> C definition."""
        self.declarations: list[str] = []
        self._symbols: dict[str, str] = {}
        self._bytes: dict[str, int] = {}
        """Bytes of const data by the condition they are compiled under ("" for always)."""

    def ref(self, value: str) -> str:
        if self.graph.is_constant(value):
            array = self.graph.constants[value]
            return self.const(value, array.reshape(-1), "constant")
        where = self.plan.storage[value]
        if where.startswith("state"):
            return f"{self.prefix}_{where}"
        if self.rows is not None:
            return f"{self.prefix}_b{where}[r]"  # the block's copy of the input, or its buffer
        return where if not where.isdigit() else f"{self.prefix}_buf{where}"

    @property
    def const_bytes(self) -> int:
        """Bytes of const data in one build: the unconditional arrays and those of the first condition
        declared (alternatives declared under other conditions are not counted)."""
        conditional = [n for condition, n in self._bytes.items() if condition]
        return self._bytes.get("", 0) + (conditional[0] if conditional else 0)

    def const(self, key: str, array: np.ndarray, comment: str, condition: str = "") -> str:
        if key in self._symbols:
            return self._symbols[key]
        symbol = f"{self.prefix}_w{len(self._symbols)}"  # an index: nothing of the model's text
        self._symbols[key] = symbol
        ctype = _INTEGER_CTYPES.get(np.asarray(array).dtype.name, "float")
        integer = ctype != "float"
        a = np.asarray(array) if integer else np.asarray(array, dtype=np.float32)
        self._bytes[condition] = self._bytes.get(condition, 0) + a.size * a.itemsize
        dims = "".join(f"[{d}]" for d in a.shape)
        lines = [const_comment(key, comment), f"static const {ctype} {symbol}{dims} = {{"]
        rows = a.reshape(1, -1) if a.ndim == 1 else a
        per_line = VALUES_PER_LINE * 3 if integer else VALUES_PER_LINE
        for r, row in enumerate(rows):
            items = [str(int(v)) for v in row] if integer else [c_float(v) for v in row]
            chunks = [", ".join(items[i : i + per_line]) for i in range(0, len(items), per_line)]
            sep = "," if r < len(rows) - 1 else ""
            if a.ndim == 1:
                lines += [
                    f"    {chunk}," if i < len(chunks) - 1 else f"    {chunk}"
                    for i, chunk in enumerate(chunks)
                ]
            else:
                lines.append("    {")
                lines += [
                    f"        {chunk}," if i < len(chunks) - 1 else f"        {chunk}"
                    for i, chunk in enumerate(chunks)
                ]
                lines.append(f"    }}{sep}")
        lines.append("};")
        if condition:
            lines = [f"#if {condition}", *lines, "#endif"]
        self.declarations.append("\n".join(lines))
        return symbol

    def literal(self, value: float) -> str:
        return c_float(value)

    def helper(self, name: str) -> str:
        needs = {"tanh_det": ["exp_det"], "sigmoid_det": ["exp_det"], "exp_det": []}[name]
        for dependency in needs:
            self.helper(dependency)
        if name not in self.helpers:
            self.helpers[name] = helper_source(self.prefix, name)
        return f"{self.prefix}_{name}"

    def function(self, name: str, source: Callable[[str], str]) -> str:
        if name not in self.helpers:
            self.helpers[name] = source(self.prefix)
        return f"{self.prefix}_{name}"

    def constant(self, value: str) -> np.ndarray | None:
        return self.graph.constants.get(value)

    def size(self, value: str) -> int:
        return self.graph.size(value)


def _with_section_output(graph: Graph, plan: _Plan, section: Section) -> _Plan:
    """Give the section's (float) output a buffer of its own after planning around the section."""
    buffer = str(len(plan.buffer_sizes))
    plan.buffer_sizes.append(graph.size(section.output))
    inside = {n.outputs[0] for n in graph.nodes if n.name in section.nodes} - {section.output}
    for value, where in plan.storage.items():
        if where == "fixed" and value not in inside:  # the output and shape-only aliases of it
            plan.storage[value] = buffer
    return plan


def _interface_block(up: str, interface: Interface | None) -> str:
    """Named indices of the interface's fields and its sample time (empty without an interface)."""
    if interface is None:
        return ""
    lines = [
        "",
        f"/* Interface {c_comment(interface.name)} ({c_comment(interface.env_id)}): index of each value in "
        "obs[] and act[]. */",
    ]
    for kind, fields in (("OBS", interface.observation), ("ACT", interface.action)):
        for i, f in enumerate(fields):
            unit = f" {c_comment(f.unit)}" if f.unit else ""
            text = f"{c_comment(f.description)}: [{f.low:.9g}, {f.high:.9g}]{unit}"
            lines.append(f"#define {up}_{kind}_{f.name.upper()} {i}u /* {text} */")
    lines.append(f"#define {up}_SAMPLE_TIME_S {c_float(interface.sample_time_s)} /* control period */")
    return "\n".join(lines) + "\n"


QUANTIZED_NOTE = {
    None: "",
    "int8-weights": ", int8 weights per output channel, float32 activations",
    "q15": ", 16-bit fixed point (int16 weights and activations, int64 sums)",
    "int8": ", full-integer int8 (int8 weights and activations, int32 sums, gemmlowp requantisation)",
}


def generate(
    graph: Graph,
    name: str = "policy",
    safe_action: Sequence[float] | None = None,
    provenance: Mapping[str, str] | None = None,
    quantize: str | None = None,
    section: Section | None = None,
    interface: Interface | None = None,
    checks: bool = True,
) -> dict[str, str]:
    """Generate ``{name}.h`` and ``{name}.c`` for ``graph`` (the deployable policy), and ``{name}_host.h`` and
    ``{name}_host.c``: the batch entry point ``{name}_step_batch`` for the host's verification and benchmarks,
    which includes ``{name}.c`` (a program is built from one of the two sources, never both).

    ``safe_action`` is written instead of the action when the observation or the result is not
    finite (default zeros); ``{NAME}_SAFE_ACTION`` in the header gives it to the CAN node's watchdog.
    ``interface`` adds a named index constant per observation and action field (``{NAME}_OBS_X``) and
    the sample time. ``provenance`` lines (e.g. hashes) go into both file headers.
    ``quantize`` is None, "int8", "int8-weights" or "q15"; int8 and q15 need the integer ``section``
    planned by :func:`export.quantize.plan_section`. ``checks=False`` leaves out the finite checks of the
    observation and the result, so ``{name}_step`` returns whatever the graph computes, NaN included: a probe
    of one op's NaN semantics for verification (:mod:`embedrl.export.nan_check`), never a deployable policy.
    """
    check_name(name)
    safe = _safe_action(graph, safe_action)
    _check_precision(graph, quantize, section)
    if section is None:
        plan = plan_buffers(graph, "obs")
    else:
        plan = _with_section_output(graph, plan_buffers(graph, "obs", section.nodes), section)
    ctx = _Context(graph, name, plan, quantize)
    body, int16_decls = _body(graph, ctx, section)
    # A recurrent step depends on the one before: its batch is a sequence, one step per row.
    block = _block(graph, ctx) if section is None and not graph.states else None
    ram = 4 * sum(plan.buffer_sizes) + (section.ram_bytes() if section else 0) + 4 * graph.state_size
    banner = "\n".join(
        [
            "/*",
            f" * {name}: policy generated by embedrl. Do not edit: regenerate with `embedrl export`.",
            *(
                f" * {identifier(k)}: {c_comment(str(v), PROVENANCE_LIMIT)}"
                for k, v in (provenance or {}).items()
            ),
            f" * observation [{graph.size(graph.input)}] -> action [{graph.size(graph.output)}], "
            f"{len(graph.nodes)} ops{QUANTIZED_NOTE[quantize]}",
            f" * RAM: {len(plan.buffer_sizes)} static buffer(s), {ram} bytes"
            + (f" with {4 * graph.state_size} bytes of recurrent state" if graph.states else "")
            + f"; weights: {ctx.const_bytes} bytes of const data",
            f" * Not reentrant: {name}_step uses file-scope buffers (one call at a time).",
            " */",
        ]
    )
    buffers = [f"static float {name}_buf{i}[{size}];" for i, size in enumerate(plan.buffer_sizes)]
    states = [
        f"static float {name}_state{k}[{graph.size(read)}]; "
        f"/* {identifier(read)}, next: {identifier(write)} */"
        for k, (read, write) in enumerate(graph.states)
    ]
    includes = section.c_includes(name) if section is not None else []
    source = _source(banner, name, ctx, body, [*states, *buffers, *int16_decls], ram, checks, includes)
    return {
        f"{name}.h": _header(banner, graph, name, safe, interface),
        f"{name}.c": source,
        **_host_files(banner, name, ctx, block),
    }


def _block(graph: Graph, ctx: _Context) -> tuple[list[str], str]:
    """The body once more for a block of up to :data:`BATCH_ROWS` observations (float32 and int8), and row
    ``r`` of the block's output (its input, if the graph computes nothing)."""
    ctx.rows = "rows"
    try:
        return _body(graph, ctx, None)[0], ctx.ref(graph.output)
    finally:
        ctx.rows = None


def _safe_action(graph: Graph, safe_action: Sequence[float] | None) -> list[float]:
    act_dim = graph.size(graph.output)
    safe = [0.0] * act_dim if safe_action is None else [float(v) for v in safe_action]
    if len(safe) != act_dim:
        raise ExportError(f"safe action has {len(safe)} values but the policy outputs {act_dim}")
    return safe


def _check_precision(graph: Graph, quantize: str | None, section: Section | None) -> None:
    from embedrl.export.quantize import SECTIONS, check_supported

    if quantize not in QUANTIZED_NOTE:
        supported = ", ".join(q for q in QUANTIZED_NOTE if q)
        raise ExportError(f"quantization {quantize!r} is not supported; supported: {supported}")
    if (quantize in SECTIONS) != (section is not None):
        raise ExportError(
            f"{quantize or 'float32'} code needs an integer section planned for it only if it is one of "
            f"{', '.join(SECTIONS)}"
        )
    if quantize:
        check_supported(graph)


def _body(graph: Graph, ctx: _Context, section: Section | None) -> tuple[list[str], list[str]]:
    """The step's lines, node by node (a q15 section as one block), and the section's int16 buffers."""
    body: list[str] = []
    int16_decls: list[str] = []
    for node in graph.nodes:
        if section is not None and node.name in section.nodes:
            if node.name == section.first_node:
                lines, int16_decls = section.c_lines(ctx)
                body += lines
            continue
        emitter = EMITTERS[node.op]
        shape_in = "x".join(str(d) for d in graph.shapes[node.inputs[0]])
        shape_out = "x".join(str(d) for d in graph.shapes[node.outputs[0]])
        attrs = ", ".join(f"{k}={v}" for k, v in sorted(node.attrs.items()))
        note = " (no code: same data)" if emitter.alias else ""
        title = c_comment(f"{node.op} '{node.name}' [{shape_in}] -> [{shape_out}]", COMMENT_LIMIT * 2)
        body.append(f"/* {title}{' ' + c_comment(attrs) if attrs else ''}{note} */")
        lines = emitter.emit(node, ctx, graph.size(node.outputs[0]))
        body += lines if ctx.rows is None or emitter.batched or not lines else per_row(lines, ctx.rows)
    return body, int16_decls


HEADER = Template("""$banner
#ifndef ${up}_H
#define ${up}_H

#include <stdint.h>

#define ${up}_OBS_DIM ${obs_dim}u
#define ${up}_ACT_DIM ${act_dim}u
#define ${up}_STATE_DIM ${state_dim}u /* floats carried from one step to the next (0: no memory) */
$interface
/* What ${name}_step writes on any non-finite value, and what a node applies when it cannot trust its input. */
#define ${up}_SAFE_ACTION {$safe}

/* Return codes of ${name}_step. */
#define ${up}_OK ((int32_t)0)
#define ${up}_ERR_OBS_NOT_FINITE ((int32_t)1) /* an observation was NaN or infinite: safe action written */
#define ${up}_ERR_ACT_NOT_FINITE ((int32_t)2) /* the network produced NaN or infinity: safe action written */

/* Run the policy on one observation. Writes ${up}_ACT_DIM actions and returns ${up}_OK, or writes the
 * safe action ($safe) and returns an error code: no NaN ever leaves it.
 * A recurrent policy (${up}_STATE_DIM > 0) reads its state and keeps the next one for the next call; a
 * non-finite observation leaves the state as it was, a non-finite result resets it. */
int32_t ${name}_step(const float obs[${up}_OBS_DIM], float act[${up}_ACT_DIM]);

/* Start a new episode: the recurrent state back to zero (nothing to do for a policy without memory).
 * Call it at start-up, at each episode start and whenever the safe state is entered. */
void ${name}_reset(void);

#endif /* ${up}_H */
""")  # noqa: E501 (the comment on the safe action, as it reads in the header)
"""``{name}.h``: the deployable policy's interface."""

HOST_HEADER = Template("""$banner
#ifndef ${up}_HOST_H
#define ${up}_HOST_H

#include "${name}.h"

/* Run the policy on n observations (obs: n rows of ${up}_OBS_DIM, act: n rows of ${up}_ACT_DIM, row-major),
 * each row's actions bit for bit those of ${name}_step, which also gives each row's code in status[] (if
 * not NULL). Returns the number of rows answered with the safe action. For host-side evaluation: it
 * reads each weight once per block of $rows rows, from its own buffers (not reentrant either).
 * With memory, the rows are one sequence: consecutive steps, the state carried from each to the next. */
int ${name}_step_batch(int n, const float *obs, float *act, int *status);

#endif /* ${up}_HOST_H */
""")
"""``{name}_host.h``: the host-only batch entry point of ``{name}_host.c``."""

HOST_SOURCE = Template("""$banner
/* Host only (verification, benchmarks, coverage on the build machine), never deployed: the batch entry
 * point over the deployable ${name}.c, which this file includes so that it reads the same weights and
 * helpers (static in ${name}.c). A program is built from this file or from ${name}.c, never both. */
#include "${name}_host.h"

#include <stddef.h>
#include <stdint.h> /* the C library's own macros (__GLIBC__), which ${up}_TARGETS' condition reads */
$targets
#if ${up}_CLONES
/* The deployable ${name}_step under the name ${name}_step_deployable, static: the host's ${name}_step below
 * inlines it into each of its clones. */
static int32_t ${name}_step_deployable(const float obs[${up}_OBS_DIM], float act[${up}_ACT_DIM]);
#define ${name}_step ${name}_step_deployable
#endif
#include "${name}.c"
#if ${up}_CLONES
#undef ${name}_step

/* ${name}_step for the host: the deployable step's code with every call it makes inlined (flatten), compiled
 * once per clone, so the host's programs run it in the CPU's instruction set with the same bits. */
${up}_TARGETS __attribute__((flatten))
int32_t ${name}_step(const float obs[${up}_OBS_DIM], float act[${up}_ACT_DIM])
{
    return ${name}_step_deployable(obs, act);
}
#endif
$body""")
"""``{name}_host.c``: the deployable source, ``{name}_step`` cloned per instruction set where
:data:`TARGETS` allows, and :data:`HOST_HEADER`'s function."""

TARGETS = Template("""
/* x86-64 glibc, gcc: ${name}_step and the batch's block compiled for each of $names, the CPU's
 * picked at load time (an ifunc); none has fused multiply-add, so every clone rounds the same operations in
 * the same order and all give the same bits. -D${up}_ONE_TARGET: the compiler's target only. */
#if defined(__GNUC__) && !defined(__clang__) && defined(__x86_64__) && defined(__GLIBC__) && \\
    !defined(${up}_ONE_TARGET)
#define ${up}_CLONES 1
#define ${up}_TARGETS __attribute__((target_clones($clones), optimize("vect-cost-model=dynamic")))
#else
#define ${up}_CLONES 0
#define ${up}_TARGETS
#endif
""")
"""The host's functions' attribute: on x86-64 with glibc (whose loader runs gcc's ifunc resolvers; musl has
none), compiled by gcc, one clone per instruction set in :data:`TARGET_CLONES`, the CPU's picked when the
program loads. No clone has a fused multiply-add instruction, so each rounds every product and sum of the
source's fixed order and all give the same bits. The clones weigh vectorising by gcc's dynamic cost model:
-O2's default takes no loop that needs a remainder after its whole vectors, which leaves a pass over 100
outputs to SSE. ``{NAME}_CLONES`` says whether the functions are cloned."""

BLOCK_BATCH = Template("""
/* A block of rows ($bytes bytes, ${name}_step_batch only): the observations, then the step's buffers, one
 * row each. */
$buffers
${up}_TARGETS
static void ${name}_block(uint32_t rows)
{
    (void)rows; /* a graph of shape-only ops computes nothing */
$block
}

/* Each row's code as ${name}_step returns it, and its actions or the safe action. */
static int32_t ${name}_finish(const float obs[${up}_OBS_DIM], const float out[${up}_ACT_DIM],
                             float act[${up}_ACT_DIM])
{
    for (uint32_t i = 0u; i < ${up}_OBS_DIM; ++i) {
        if (!${name}_finite(obs[i])) {
            return ${name}_safe(act, ${up}_ERR_OBS_NOT_FINITE);
        }
    }
    for (uint32_t i = 0u; i < ${up}_ACT_DIM; ++i) {
        if (!${name}_finite(out[i])) {
            return ${name}_safe(act, ${up}_ERR_ACT_NOT_FINITE);
        }
    }
    for (uint32_t i = 0u; i < ${up}_ACT_DIM; ++i) {
        act[i] = out[i];
    }
    return ${up}_OK;
}

int ${name}_step_batch(int n, const float *obs, float *act, int *status)
{
    int refused = 0;
    for (int start = 0; start < n; start += $rows) {
        const int rows = n - start < $rows ? n - start : $rows;
        for (int r = 0; r < rows; ++r) {
            for (uint32_t i = 0u; i < ${up}_OBS_DIM; ++i) {
                ${name}_bobs[r][i] = obs[(size_t)(start + r) * ${up}_OBS_DIM + i];
            }
        }
        ${name}_block((uint32_t)rows);
        for (int r = 0; r < rows; ++r) {
            const size_t row = (size_t)(start + r);
            const int32_t code = ${name}_finish(&obs[row * ${up}_OBS_DIM], $out, &act[row * ${up}_ACT_DIM]);
            if (status != NULL) {
                status[row] = code;
            }
            refused += code != ${up}_OK ? 1 : 0;
        }
    }
    return refused;
}
""")
"""``{name}_step_batch`` over blocks of :data:`BATCH_ROWS` rows (float32 and int8), the finite checks per row
after the block."""

ROW_BATCH = Template("""
int ${name}_step_batch(int n, const float *obs, float *act, int *status)
{
    int refused = 0;
    for (int i = 0; i < n; ++i) {
        const size_t row = (size_t)i;
        const int32_t code = ${name}_step(&obs[row * ${up}_OBS_DIM], &act[row * ${up}_ACT_DIM]);
        if (status != NULL) {
            status[row] = code;
        }
        refused += code != ${up}_OK ? 1 : 0;
    }
    return refused;
}
""")
"""``{name}_step_batch`` as one step per row (q15 and int8-full: an integer section works on one row; a
recurrent policy: each step depends on the one before)."""


def _header(banner: str, graph: Graph, name: str, safe: list[float], interface: Interface | None) -> str:
    up = name.upper()
    return HEADER.substitute(
        banner=banner, up=up, name=name, obs_dim=graph.size(graph.input), act_dim=graph.size(graph.output),
        state_dim=graph.state_size, interface=_interface_block(up, interface),
        safe=", ".join(c_float(v) for v in safe),
    )  # fmt: skip


def _host_files(banner: str, name: str, ctx: _Context, block: tuple[list[str], str] | None) -> dict[str, str]:
    """``{name}_host.h`` and ``{name}_host.c``: the cloned step and the batch entry point, for the host's
    builds only."""
    up = name.upper()
    if block is None:
        body = ROW_BATCH.substitute(name=name, up=up)
    else:
        sizes = [ctx.graph.size(ctx.graph.input), *ctx.plan.buffer_sizes]
        names = ["obs", *(str(i) for i in range(len(ctx.plan.buffer_sizes)))]
        buffers = "\n".join(
            f"static float {name}_b{b}[{BATCH_ROWS}][{size}];" for b, size in zip(names, sizes, strict=True)
        )
        lines, out = block
        body = BLOCK_BATCH.substitute(
            name=name, up=up, bytes=4 * BATCH_ROWS * sum(sizes), buffers=buffers, rows=BATCH_ROWS, out=out,
            block="\n".join(("    " + line) if line else "" for line in lines),
        )  # fmt: skip
    clones = ", ".join(f'"{t}"' for t in TARGET_CLONES)
    targets = TARGETS.substitute(up=up, name=name, names=", ".join(TARGET_CLONES), clones=clones)
    return {
        f"{name}{HOST_STEM}.h": HOST_HEADER.substitute(banner=banner, up=up, name=name, rows=BATCH_ROWS),
        f"{name}{HOST_SUFFIX}": HOST_SOURCE.substitute(
            banner=banner, name=name, up=up, targets=targets, body=body
        ),
    }


def _state_lines(name: str, ctx: _Context) -> tuple[str, str, str]:
    """The reset's body, the finite check of the next state, and its copy into the static state."""
    graph = ctx.graph
    if not graph.states:
        return "    /* no recurrent state */", "", ""
    reset, check, keep = [], [], []
    for k, (read, write) in enumerate(graph.states):
        n, src = graph.size(read), ctx.ref(write)
        reset.append(f"    (void)memset({name}_state{k}, 0, sizeof {name}_state{k});")
        check += [
            f"    for (uint32_t i = 0u; i < {n}u; ++i) {{",
            f"        if (!{name}_finite({src}[i])) {{",
            f"            {name}_reset();",
            f"            return {name}_safe(act, {name.upper()}_ERR_ACT_NOT_FINITE);",
            "        }",
            "    }",
        ]
        keep += [
            f"    for (uint32_t i = 0u; i < {n}u; ++i) {{",
            f"        {name}_state{k}[i] = {src}[i];",
            "    }",
        ]
    return "\n".join(reset), "\n".join(check) + "\n", "\n".join(keep) + "\n"


SOURCE = Template("""$banner
#include "${name}.h"

#include <math.h>
#include <stdbool.h>
#include <stdint.h>
$string_h$includes
$declarations

static const float ${name}_safe_action[${up}_ACT_DIM] = ${up}_SAFE_ACTION;

/* Scratch buffers ($ram bytes). */
$buffers
$helpers
/* Finite test on the float's bits (exponent not all ones): it holds under -ffast-math, which lets a
 * compiler assume that no NaN or infinity exists and drop isfinite(). */
static bool ${name}_finite(float x)
{
    union {
        float f;
        uint32_t u;
    } bits;
    bits.f = x;
    return (bits.u & 0x7f800000u) != 0x7f800000u;
}

static int32_t ${name}_safe(float act[${up}_ACT_DIM], int32_t code)
{
    for (uint32_t i = 0u; i < ${up}_ACT_DIM; ++i) {
        act[i] = ${name}_safe_action[i];
    }
    return code;
}

void ${name}_reset(void)
{
$reset
}

int32_t ${name}_step(const float obs[${up}_OBS_DIM], float act[${up}_ACT_DIM])
{
$check_obs$body
$check_act$check_state$keep_state    for (uint32_t i = 0u; i < ${up}_ACT_DIM; ++i) {
        act[i] = ${out}[i];
    }
    return ${up}_OK;
}
""")
"""``{name}.c``: the deployable policy (weights, buffers, helpers, ``{name}_reset`` and ``{name}_step``)."""

CHECK_OBS = Template("""    for (uint32_t i = 0u; i < ${up}_OBS_DIM; ++i) {
        if (!${name}_finite(obs[i])) {
            return ${name}_safe(act, ${up}_ERR_OBS_NOT_FINITE);
        }
    }
""")
"""The step's refusal of a non-finite observation."""

CHECK_ACT = Template("""    for (uint32_t i = 0u; i < ${up}_ACT_DIM; ++i) {
        if (!${name}_finite(${out}[i])) {
            ${reset}return ${name}_safe(act, ${up}_ERR_ACT_NOT_FINITE);
        }
    }
""")
"""The step's refusal of a non-finite result (``reset``: the recurrent state's reset first, if any)."""


def _source(
    banner: str,
    name: str,
    ctx: _Context,
    body: list[str],
    buffers: list[str],
    ram: int,
    checks: bool,
    includes: list[str],
) -> str:
    up = name.upper()
    out_ref = ctx.ref(ctx.graph.output)
    reset, check_state, keep_state = _state_lines(name, ctx)
    check_obs = CHECK_OBS.substitute(up=up, name=name)
    act_bad = f"{name}_reset();\n            " if ctx.graph.states else ""
    check_act = CHECK_ACT.substitute(up=up, name=name, out=out_ref, reset=act_bad)
    if not checks:
        check_obs = check_act = check_state = ""
    return SOURCE.substitute(
        banner=banner, name=name, up=up, ram=ram, reset=reset, out=out_ref,
        string_h="#include <string.h>\n" if ctx.graph.states else "",  # memset of the recurrent state
        includes="".join("\n" + line for line in includes) + ("\n" if includes else ""),
        declarations="\n".join(ctx.declarations),
        buffers="\n".join(buffers) if buffers else "/* none */",
        helpers="".join("\n" + h + "\n" for h in ctx.helpers.values()),
        check_obs=check_obs, check_act=check_act, check_state=check_state, keep_state=keep_state,
        body="\n".join(("    " + line) if line else "" for line in body),
    )  # fmt: skip
