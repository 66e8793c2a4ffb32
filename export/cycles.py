"""Time on the target: instructions per inference measured on QEMU, and cycles estimated from the core's
instruction timings.

**Instructions** are counted, not estimated: QEMU runs the test image with ``-icount shift=0`` (virtual
time advances 1 ns per guest instruction), so the board's timer ticks once per a fixed number of
instructions (the target table's ``TICK``: 40 for the MPS2 boards' 25 MHz timer, 1 for the STM32F405's TIM2,
which QEMU runs at 1 GHz, 125/3 for the STM32F100's SysTick at 24 MHz); the image times a loop of
``policy_step`` over its test observations and the same loop around an empty function, and the difference
over the count is the instructions of one inference (to ``TICK`` / count instructions).

**Cycles** are estimated: one inference of the size probe (``policy.elf``) is traced instruction by
instruction (``-singlestep -d exec``), each executed instruction is classed from the image's disassembly,
and each class costs what the core's technical reference manual lists (:data:`CYCLE_MODELS`, with a taken
branch told from the next traced address). The estimate's cycles per instruction times the measured
instructions is the cycle estimate. Wait states of a real part's flash are not modelled (the STM32F405
at 168 MHz has 5 flash wait states at 3.3 V, RM0090 table 10, which its ART accelerator hides when it
hits; the STM32F100 value line runs its flash with 0 wait states at its 24 MHz maximum, so its estimate
needs no such caveat: a part running from zero-wait-state memory, or with its accelerator hitting, matches
the model best);
:data:`ASSUMPTIONS` states what the estimate takes for granted, for the report.
"""

from __future__ import annotations

import re
import subprocess
from collections import Counter
from dataclasses import dataclass
from pathlib import Path
from typing import Any

from embedrl.common import owned_temporary_folder
from embedrl.export.errors import ExportError

ICOUNT = ("-icount", "shift=0")
TRACE_TIMEOUT_S = 120
CONDITIONS = {
    "eq",
    "ne",
    "cs",
    "cc",
    "hs",
    "lo",
    "mi",
    "pl",
    "vs",
    "vc",
    "hi",
    "ls",
    "ge",
    "lt",
    "gt",
    "le",
    "al",
}


ASSUMPTIONS = (
    ("clock", "the modelled part's core clock (below); the time is the estimated cycles over it"),
    ("flash wait states", "not in the model: every fetch and constant load costs what the technical "
     "reference manual lists for zero-wait-state memory; a part whose flash needs wait states at this clock "
     "is slower unless its prefetch buffer or flash accelerator hits"),
    ("caches, dual issue, bus contention", "not in the model (the Cortex-M7 takes the Cortex-M4 table, an "
     "upper bound for its dual issue)"),
    ("instructions", "counted on QEMU (-icount), not estimated: the model only prices them, from one traced "
     "inference's mix of instruction classes"),
    ("interrupts", "none during the inference (the firmware node's worst step is measured separately)"),
)  # fmt: skip
"""What the cycle estimate assumes, as (topic, statement) rows."""


@dataclass(frozen=True)
class CycleModel:
    """Cycles per instruction class of one core (``N``: registers transferred; taken branches refill the
    pipeline)."""

    source: str
    clock_hz: int
    """The clock of the part the target table models, for the margin to the sample time."""
    part: str
    cycles: dict[str, float]
    """Class -> cycles; ``load_multiple`` and ``store_multiple`` cost ``1 + N`` (the entry is the 1)."""


_M4 = {
    "alu": 1, "load": 2, "store": 2, "load_multiple": 1, "store_multiple": 1, "branch_taken": 3,
    "branch_not_taken": 1, "multiply": 1, "multiply_accumulate": 2, "long_multiply": 1, "divide": 7,
    "fp_alu": 1, "fp_multiply_accumulate": 3, "fp_divide": 14, "fp_load": 2, "fp_store": 2,
}  # fmt: skip
CYCLE_MODELS = {
    "cortex-m4": CycleModel(
        "Cortex-M4 TRM (ARM DDI 0439B) table 3-1 and FPv4-SP timings (table 7-1): LDR/STR 2, "
        "LDM/STM/PUSH/POP 1+N, taken branch 1+P with P = 2, MUL 1, MLA 2, UMULL 1, SDIV 2-12 (7), "
        "VADD/VMUL 1, VMLA/VFMA 3, VDIV/VSQRT 14, VLDR/VSTR 2, VLDM/VPUSH 1+N, other data processing 1",
        168_000_000, "STM32F405 at 168 MHz", dict(_M4),
    ),
    "cortex-m3": CycleModel(
        "Cortex-M3 TRM (ARM DDI 0337H) table 18-1: LDR/STR 2, LDM/STM/PUSH/POP 1+N, taken branch 1+P with "
        "P = 2, MUL 1, MLA 2, UMULL/SMULL 3-5 (4), SDIV 2-12 (7), other data processing 1; no FPU (floating "
        "point in library calls, counted as their instructions); the STM32F100 runs its flash with 0 wait "
        "states at 24 MHz (ST's system_stm32f10x.c sets no flash latency on value-line parts), so the table "
        "holds for its fetches",
        24_000_000, "STM32F100RB at 24 MHz", {**_M4, "long_multiply": 4},
    ),
    "cortex-m7": CycleModel(
        "The Cortex-M4 table as an upper bound: the Cortex-M7's TRM publishes no per-instruction timings, "
        "and its dual issue retires up to two instructions per cycle",
        216_000_000, "STM32F7 at 216 MHz", dict(_M4),
    ),
}  # fmt: skip


def instructions_per_inference(report_lines: list[str], tick_instructions: float) -> float:
    """From the test image's ``TICKS <policy> <empty> <count>`` line (run under :data:`ICOUNT`)."""
    rows = [line.split() for line in report_lines if line.startswith("TICKS ")]
    if len(rows) != 1 or len(rows[0]) != 4:
        raise ExportError(f"the firmware printed no single TICKS line: {rows}")
    policy, empty, count = (int(v) for v in rows[0][1:])
    return (policy - empty) * tick_instructions / count


FP_CLASSES: tuple[tuple[tuple[str, ...], str], ...] = (
    (("vldm", "vpop"), "load_multiple"), (("vstm", "vpush"), "store_multiple"),
    (("vldr",), "fp_load"), (("vstr",), "fp_store"), (("vdiv", "vsqrt"), "fp_divide"),
    (("vmla", "vmls", "vnmla", "vnmls", "vfma", "vfms", "vfnma", "vfnms"), "fp_multiply_accumulate"),
)  # fmt: skip
"""Floating-point mnemonic stems and their class (any other ``v`` instruction: ``fp_alu``)."""
INTEGER_CLASSES: tuple[tuple[tuple[str, ...], str], ...] = (
    (("ldm", "pop"), "load_multiple"), (("stm", "push"), "store_multiple"), (("ldr",), "load"),
    (("str",), "store"), (("sdiv", "udiv"), "divide"),
    (("smull", "umull", "smlal", "umlal"), "long_multiply"), (("mla", "mls"), "multiply_accumulate"),
    (("mul",), "multiply"),
)  # fmt: skip
"""Integer mnemonic stems and their class (branches are told apart below; the rest: ``alu``)."""


def _classify(mnemonic: str) -> str:
    """The cycle class of an instruction mnemonic (condition codes and width suffixes removed)."""
    m = mnemonic.lower().split(".")[0]
    table = FP_CLASSES if m.startswith("v") else INTEGER_CLASSES
    for stems, cls in table:
        if m.startswith(stems):
            return cls
    if m.startswith("v"):
        return "fp_alu"
    if m in ("b", "bl", "blx", "bx", "cbz", "cbnz") or (m[:1] == "b" and m[1:] in CONDITIONS):
        return "branch"
    return "alu"


def _registers(operands: str) -> int:
    """Registers in a list operand such as ``{r4, r5, lr}``, ``{s16-s21}`` or ``{d8-d9}`` (words moved)."""
    inside = operands[operands.find("{") + 1 : operands.find("}")]
    words = 0
    for part in (p.strip() for p in inside.split(",") if p.strip()):
        ends = [int(re.sub(r"\D", "", e) or 0) for e in part.split("-")]
        count = ends[-1] - ends[0] + 1 if len(ends) == 2 else 1
        words += count * (2 if part.startswith("d") else 1)
    return words


def _disassembly(elf: Path) -> dict[int, tuple[str, str, int]]:
    """Address -> (mnemonic, operands, size in bytes) of every instruction in the image."""
    text = subprocess.run(
        ["arm-none-eabi-objdump", "-d", "--no-show-raw-insn", str(elf)],
        capture_output=True,
        text=True,
        check=True,
    ).stdout
    found = re.findall(r"^\s*([0-9a-f]+):\s+([a-z][\w.]*)\s*([^;<\n]*)", text, re.M)
    rows = sorted((int(a, 16), m, ops.strip()) for a, m, ops in found)
    return {
        addr: (m, ops, (rows[i + 1][0] - addr) if i + 1 < len(rows) else 4)
        for i, (addr, m, ops) in enumerate(rows)
    }


def _trace(elf: Path, machine: str) -> list[tuple[int, str]]:
    """(address, function) of every instruction QEMU executed running ``elf`` to its exit."""
    with owned_temporary_folder("embedrl-trace-") as tmp:
        log = tmp / "exec.log"
        cmd = ["qemu-system-arm", "-M", machine, "-nographic", "-monitor", "none", "-semihosting",
               "-singlestep", "-d", "exec,nochain", "-D", str(log), "-kernel", str(elf)]  # fmt: skip
        try:
            subprocess.run(cmd, capture_output=True, timeout=TRACE_TIMEOUT_S, check=False)
        except subprocess.TimeoutExpired:
            raise ExportError(f"tracing {elf.name} on QEMU took over {TRACE_TIMEOUT_S} s") from None
        pattern = re.compile(r"^Trace \d+: 0x[0-9a-f]+ \[[0-9a-f]+/([0-9a-f]+)/[^\]]*\] ?(\S*)")
        return [
            (int(m.group(1), 16), m.group(2)) for m in map(pattern.match, log.read_text().splitlines()) if m
        ]


def profile(elf: Path, machine: str, target: str, function: str = "policy_step") -> dict[str, Any]:
    """One inference of the probe ``elf`` (``policy.elf``: main calls ``function`` once), traced from
    ``function``'s entry to the return into ``main``: its instruction classes and the cycles the target's
    model gives them."""
    model = CYCLE_MODELS[target]
    trace = _trace(elf, machine)
    starts = [i for i, (_, fn) in enumerate(trace) if fn == function]
    if not starts:
        raise ExportError(f"{elf.name}: {function} never ran in the trace")
    begin = starts[0]
    end = next((i for i in range(begin, len(trace)) if trace[i][1] == "main"), len(trace))
    code = _disassembly(elf)
    classes: Counter[str] = Counter()
    cycles = 0.0
    for i in range(begin, end):
        pc = trace[i][0]
        mnemonic, operands, size = code.get(pc, ("?", "", 2))
        cls = _classify(mnemonic)
        if cls == "branch":
            taken = i + 1 < len(trace) and trace[i + 1][0] != pc + size
            cls = "branch_taken" if taken else "branch_not_taken"
        cost = model.cycles[cls]
        if cls in ("load_multiple", "store_multiple"):
            cost += _registers(operands)
        classes[cls] += 1
        cycles += cost
    instructions = end - begin
    return {
        "traced_instructions": instructions,
        "traced_cycles": cycles,
        "cycles_per_instruction": cycles / instructions,
        "instruction_classes": dict(sorted(classes.items())),
    }


def time_on_target(
    instructions: float, traced: dict[str, Any], target: str, sample_time_s: float | None
) -> dict[str, Any]:
    """The report's figures: instructions, estimated cycles, the model, and the time and margin at the
    modelled part's clock."""
    model = CYCLE_MODELS[target]
    cycles = instructions * traced["cycles_per_instruction"]
    seconds = cycles / model.clock_hz
    return {
        "instructions_per_inference": round(instructions, 1),
        "estimated_cycles_per_inference": round(cycles),
        "cycle_model": {"source": model.source, "cycles": model.cycles, **traced},
        "clock": {"part": model.part, "hz": model.clock_hz},
        "estimated_inference_us": round(seconds * 1e6, 2),
        "sample_time_s": sample_time_s,
        "fraction_of_sample_time": None if not sample_time_s else round(seconds / sample_time_s, 6),
    }
