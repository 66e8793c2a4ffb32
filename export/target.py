"""Bare-metal Cortex-M targets: build the generated C into firmware, run it under QEMU, measure it.

The firmware (``make -C runtime_c TARGET=...``) runs the policy on observations embedded at build
time and prints the action bits through semihosting; they are compared with a reference computed
on the host. Sizes come from the linked images: the policy's cost is the difference between an
image that calls ``policy_step`` and one that does not (so it includes the library routines the
policy pulls in, such as libm or software floating point), its RAM adds the measured peak stack.
"""

from __future__ import annotations

import re
import shutil
import subprocess
from dataclasses import dataclass
from fractions import Fraction
from pathlib import Path
from typing import Any

import numpy as np

from embedrl.common import read_json
from embedrl.export import build, cycles, stack
from embedrl.export.contract.literals import c_float
from embedrl.export.errors import BuildError, ExportError

TEST_VECTOR_COUNT = 256
"""Observations embedded in the test image (half uniform, half recorded from rollouts)."""
QEMU_TIMEOUT_S = 300
APT_PACKAGES = "gcc-arm-none-eabi libnewlib-arm-none-eabi qemu-system-arm"


@dataclass(frozen=True)
class Target:
    """A Cortex-M core, the QEMU machine that emulates it, and the part whose memory it models."""

    name: str
    qemu_machine: str
    flash_kib: int
    ram_kib: int
    part: str
    cpu_flags: str
    board: str
    """The board file (``runtime_c/cortex_m/boards/<board>/board.h``)."""
    tick_instructions: float
    """Guest instructions per tick of the board's timer under ``-icount shift=0`` (125/3 for the STM32F100's
    SysTick at 24 MHz)."""

    @property
    def has_fpu(self) -> bool:
        """Built for the hard-float ABI: interrupts stack the floating-point context too."""
        return "-mfloat-abi=hard" in self.cpu_flags


TARGET_TABLE = build.RUNTIME_C / "cortex_m" / "targets.mk"
"""The one table of targets, read by the Makefile too (which writes each linker script's memory from it)."""
_ENTRY = re.compile(r"^([\w-]+)\.(CPU|BOARD|FLASH|FLASH_AT|RAM|QEMU|TICK|PART)\s*:=\s*(.*?)\s*$")


def load_targets(table: Path = TARGET_TABLE) -> dict[str, Target]:
    """The targets of ``targets.mk`` (``<name>.KEY := value`` lines), in their order."""
    entries: dict[str, dict[str, str]] = {}
    for line in table.read_text().splitlines():
        match = _ENTRY.match(line)
        if match:
            entries.setdefault(match.group(1), {})[match.group(2)] = match.group(3)
    return {
        name: Target(
            name,
            e["QEMU"],
            int(e["FLASH"]),
            int(e["RAM"]),
            e["PART"],
            e["CPU"],
            e["BOARD"],
            float(Fraction(e["TICK"])),
        )
        for name, e in entries.items()
    }


TARGETS = load_targets()


def test_vectors_source(observations: np.ndarray) -> str:
    """C source defining the test image's observations (exact float literals)."""
    rows = ",\n".join("    {" + ", ".join(c_float(v) for v in row) + "}" for row in observations)
    return (
        "/* Observations for the Cortex-M test image, written by embedrl export. Do not edit. */\n"
        f"const unsigned embedrl_test_count = {len(observations)}u;\n"
        f"const float embedrl_test_obs[{len(observations)}][{observations.shape[1]}] = {{\n{rows}\n}};\n"
    )


def pick_test_vectors(samples: np.ndarray, from_rollouts: int) -> np.ndarray:
    """TEST_VECTOR_COUNT observations spread over the uniform and the recorded samples."""
    uniform, recorded = samples[: len(samples) - from_rollouts], samples[len(samples) - from_rollouts :]
    half = TEST_VECTOR_COUNT // 2
    parts = [
        p[np.linspace(0, len(p) - 1, min(len(p), half)).astype(int)] for p in (uniform, recorded) if len(p)
    ]
    picked = np.concatenate(parts)
    if len(picked) < TEST_VECTOR_COUNT:
        extra = uniform[np.linspace(0, len(uniform) - 1, TEST_VECTOR_COUNT - len(picked)).astype(int)]
        picked = np.concatenate([picked, extra])
    return np.ascontiguousarray(picked[:TEST_VECTOR_COUNT], dtype=np.float32)


def _require(tool: str) -> None:
    if shutil.which(tool) is None:
        raise ExportError(f"{tool} not found: install the Debian packages {APT_PACKAGES} (make deps)")


def build_firmware(target: Target, c_dir: Path, vectors: Path, build_dir: Path) -> Path:
    """Build the test image and the size probes; a policy too large for the part is a clear error."""
    _require("arm-none-eabi-gcc")
    try:
        build.make(
            "firmware",
            c_dir,
            build_dir,
            extra={"TARGET": target.name, "TEST_VECTORS": str(vectors.resolve())},
        )
    except BuildError as exc:
        refused = build.FIT_REFUSAL.match(str(exc))
        if refused:
            part = target.part.split(", ")[-1]
            raise ExportError(
                f"{target.name}: the policy does not fit the {part}: {refused.group(4)}"
            ) from None
        raise
    return build_dir / target.name


@dataclass(frozen=True)
class TargetRun:
    actions: np.ndarray
    codes: np.ndarray
    stack_bytes: int
    instructions_per_inference: float
    """Measured under ``-icount`` (:func:`embedrl.export.cycles.instructions_per_inference`)."""


def run_qemu(target: Target, firmware: Path, count: int, act_dim: int) -> TargetRun:
    """Run the test image on QEMU and parse what it reports through semihosting."""
    _require("qemu-system-arm")
    cmd = [
        "qemu-system-arm",
        "-M",
        target.qemu_machine,
        "-nographic",
        "-monitor",
        "none",
        "-semihosting",
        *cycles.ICOUNT,  # the timer counts instructions (the image's TICKS line)
        "-kernel",
        str(firmware),
    ]
    try:
        result = subprocess.run(cmd, capture_output=True, text=True, timeout=QEMU_TIMEOUT_S)
    except subprocess.TimeoutExpired:
        raise ExportError(
            f"{target.name}: the firmware did not finish within {QEMU_TIMEOUT_S} s on QEMU"
        ) from None
    if result.returncode != 0:
        raise ExportError(
            f"{target.name}: the firmware exited with status {result.returncode} "
            f"on QEMU {target.qemu_machine} (3 is a fault): {(result.stdout + result.stderr).strip()[-300:]}"
        )
    lines = result.stdout.splitlines()
    stack = [int(line.split()[1]) for line in lines if line.startswith("STACK ")]
    rows = [line.split() for line in lines if line.startswith("A ")]
    if len(stack) != 1 or len(rows) != count or f"DONE {count}" not in lines:
        raise ExportError(f"{target.name}: unexpected firmware output: {result.stdout[:300]!r}")
    bits = np.array([[int(h, 16) for h in row[3:]] for row in rows], dtype=np.uint32)
    if bits.shape != (count, act_dim):
        raise ExportError(
            f"{target.name}: the firmware printed {bits.shape[1]} actions per line, expected {act_dim}"
        )
    instructions = cycles.instructions_per_inference(lines, target.tick_instructions)
    return TargetRun(bits.view(np.float32), np.array([int(row[2]) for row in rows]), stack[0], instructions)


def sizes(out: Path, stack_bytes: int) -> dict[str, int]:
    """Policy flash and RAM (difference of the probe images plus the stack) and the test image's."""
    policy, empty, image = (elf_size(out / f"{name}.elf") for name in ("policy", "empty", "firmware"))
    return {
        "flash_bytes": (policy["text"] + policy["data"]) - (empty["text"] + empty["data"]),
        "ram_bytes": (policy["data"] + policy["bss"]) - (empty["data"] + empty["bss"]) + stack_bytes,
        "stack_bytes": stack_bytes,
        "image_flash_bytes": image["text"] + image["data"],
        "image_ram_bytes": image["data"] + image["bss"],
    }


def node_firmware(target: Target, c_dir: Path, build_dir: Path) -> dict[str, Any]:
    """The firmware node of this policy (``make TARGET=... node``): its flash, its static RAM and its
    worst-case stack (:func:`embedrl.export.stack.node_bound`)."""
    build.make("node", c_dir, build_dir, extra={"TARGET": target.name})
    elf = build_dir / target.name / "node.elf"
    size = elf_size(elf)
    return {
        "flash_bytes": size["text"] + size["data"],
        "image_ram_bytes": size["data"] + size["bss"],  # with the linker's stack and heap reservations
        "stack_bound": stack.node_bound(elf, fpu=target.has_fpu),
    }


def elf_size(elf: Path) -> dict[str, int]:
    """``text``, ``data`` and ``bss`` of an image (arm-none-eabi-size)."""
    out = subprocess.run(["arm-none-eabi-size", str(elf)], capture_output=True, text=True, check=True).stdout
    text, data, bss = (int(v) for v in out.splitlines()[1].split()[:3])
    return {"text": text, "data": data, "bss": bss}


def cycles_per_instruction(export_dir: Path, target: str, work: Path) -> dict[str, Any]:
    """The traced inference of ``target`` for an export: from its ``export_report.json`` when it was
    exported with ``--target``, else traced now from the size probe built in ``work``."""
    report = export_dir / "export_report.json"
    if report.is_file():
        known = read_json(report).get("targets", {}).get(target)
        if known and "cycle_model" in known:
            model: dict[str, Any] = known["cycle_model"]
            return {k: model[k] for k in ("traced_instructions", "traced_cycles", "cycles_per_instruction",
                                          "instruction_classes")}  # fmt: skip
    t = TARGETS[target]
    out = build_firmware(t, export_dir / "c", export_dir / "test" / "test_vectors.c", work)
    return cycles.profile(out / "policy.elf", t.qemu_machine, target)
