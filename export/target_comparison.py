"""Time on the target beside a peer: embedrl's generated C and emx-onnx-cgen's C of the same ONNX, built for
the same Cortex-M cores, run on QEMU and traced in one run (``embedrl bench-target``).

Both are measured the same way (:mod:`embedrl.export.cycles`): instructions per inference counted under
``-icount`` over the export's 256 test observations (a timed loop minus the same loop around an empty call),
cycles estimated from one traced inference and the core's instruction timings. The peer's actions are
checked against embedrl's first (within 1e-5), so the two compute the same policy. emx-onnx-cgen is not a
dependency: it is installed into ``tools/`` by ``make bench-target`` and named with ``--emx``. It generates
float32 C only: a quantised export is measured alone, its cycles per multiply-add set beside the float32
export's run. Each figure carries the graph's multiply-adds per inference and the cycles per multiply-add.
"""

from __future__ import annotations

import subprocess
from pathlib import Path
from typing import Any

import numpy as np

from embedrl.common import owned_temporary_folder, read_json
from embedrl.export import build, cycles, target
from embedrl.export.errors import ExportError
from embedrl.export.onnx_import import load_onnx
from embedrl.export.ops import graph_multiply_adds
from embedrl.export.qdq import lowered
from embedrl.train.interface import INTERFACE_FILE, Interface

AGREEMENT = 1e-5
"""The peer's actions against embedrl's on the same observations (float32 generators)."""
EMX_VERSION = "1.4.0"


def _actions(lines: list[str], count: int) -> np.ndarray:
    rows = [line.split() for line in lines if line.startswith("A ")]
    if len(rows) != count:
        raise ExportError(f"the peer image printed {len(rows)} actions, expected {count}")
    return np.array([[int(h, 16) for h in row[2:]] for row in rows], dtype=np.uint32).view(np.float32)


def _run(t: target.Target, elf: Path) -> list[str]:
    result = subprocess.run(
        ["qemu-system-arm", "-M", t.qemu_machine, "-nographic", "-monitor", "none", "-semihosting",
         *cycles.ICOUNT, "-kernel", str(elf)],
        capture_output=True, text=True, timeout=target.QEMU_TIMEOUT_S,
    )  # fmt: skip
    if result.returncode != 0:
        raise ExportError(f"{elf.name} exited with status {result.returncode} on {t.qemu_machine}")
    return result.stdout.splitlines()


def _figures(
    t: target.Target, instructions: float, traced: dict[str, Any], flash: int, macs: int
) -> dict[str, Any]:
    timed = cycles.time_on_target(instructions, traced, t.name, None)
    return {
        "instructions_per_inference": timed["instructions_per_inference"],
        "estimated_cycles_per_inference": timed["estimated_cycles_per_inference"],
        "multiply_adds": macs,
        "estimated_cycles_per_multiply_add": round(timed["estimated_cycles_per_inference"] / macs, 2),
        "cycles_per_instruction": round(traced["cycles_per_instruction"], 3),
        "estimated_inference_us": timed["estimated_inference_us"],
        "flash_bytes": flash,
    }


def measure(export_dir: Path, target_name: str, emx: Path | None, work: Path) -> dict[str, Any]:
    """embedrl's and the peer's figures on one target, and their ratios (peer / embedrl); embedrl's alone
    when ``emx`` is None."""
    t = target.TARGETS[target_name]
    macs = graph_multiply_adds(lowered(load_onnx(export_dir / "policy.onnx"))[0])
    c_dir, vectors = export_dir / "c", export_dir / "test" / "test_vectors.c"
    out = target.build_firmware(t, c_dir, vectors, work)
    interface = Interface.from_json(read_json(export_dir / INTERFACE_FILE))
    run = target.run_qemu(t, out / "firmware.elf", 256, len(interface.action))
    ours = _figures(
        t, run.instructions_per_inference, cycles.profile(out / "policy.elf", t.qemu_machine, t.name),
        _flash(out / "policy.elf") - _flash(out / "empty.elf"), macs,
    )  # fmt: skip
    if emx is None:
        return {"target": t.name, "part": t.part, "embedrl": ours}
    peer_c = work / "peer.c"
    generated = subprocess.run(
        [str(emx), "compile", str(export_dir / "policy.onnx"), str(peer_c), "--model-name", "peer"],
        capture_output=True, text=True,
    )  # fmt: skip
    if generated.returncode != 0:
        raise ExportError(f"emx-onnx-cgen could not compile the policy: {generated.stderr.strip()[-300:]}")
    build.make("peer", c_dir, work, extra={"TARGET": t.name, "TEST_VECTORS": str(vectors.resolve()),
                                            "PEER_C": str(peer_c)})  # fmt: skip
    lines = _run(t, out / "peer.elf")
    agreement = float(np.max(np.abs(_actions(lines, len(run.actions)) - run.actions)))
    if not agreement <= AGREEMENT:
        raise ExportError(f"{t.name}: the peer's actions differ from embedrl's by {agreement:.3g}")
    peer_flash = _flash(out / "peer_probe.elf") - _flash(out / "empty.elf")
    peer = _figures(
        t, cycles.instructions_per_inference(lines, t.tick_instructions),
        cycles.profile(out / "peer_probe.elf", t.qemu_machine, t.name, function="peer"), peer_flash, macs,
    )  # fmt: skip
    return {
        "target": t.name,
        "part": t.part,
        "embedrl": ours,
        "emx_onnx_cgen": peer,
        "max_action_difference": agreement,
        "ratio_instructions": round(
            peer["instructions_per_inference"] / ours["instructions_per_inference"], 3
        ),
        "ratio_cycles": round(
            peer["estimated_cycles_per_inference"] / ours["estimated_cycles_per_inference"], 3
        ),
    }


def _ratio(peer: dict[str, Any], ours: dict[str, Any], key: str) -> float:
    return round(float(peer[key]) / float(ours[key]), 3)


def _flash(elf: Path) -> int:
    size = target.elf_size(elf)
    return size["text"] + size["data"]


def run(export_dir: Path, targets: list[str], emx: Path | None) -> dict[str, Any]:
    """Every target measured, in a temporary build folder (without a peer when ``emx`` is None)."""
    if emx is not None and not emx.is_file():
        raise ExportError(f"no emx-onnx-cgen at {emx}: `make bench-target` installs it into tools/emx")
    with owned_temporary_folder("embedrl-target-bench-") as tmp:
        return {
            "export": str(export_dir),
            "peer": None if emx is None else f"emx-onnx-cgen {EMX_VERSION}",
            "targets": [measure(export_dir, name, emx, Path(tmp) / name) for name in targets],
        }
