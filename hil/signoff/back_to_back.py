"""The back-to-back table of the deployment report: the policy's action at each link of the chain from the
trained model to the bus, SB3's ``predict`` -> ONNX (onnxruntime) -> the C on the host -> the C on each
Cortex-M target -> the action a node sent on the bus, with the largest absolute difference and the largest
distance in float32 steps (ULP) between the two ends of each link.

SB3 -> ONNX is the export's own figure (the report never loads the SB3 zip: loading unpickles it); ONNX ->
host C is the report's recomputation; host C -> firmware is measured again here, the verified C built for
the target and run under QEMU on the export's test vectors; the bus link is the HIL run's figure (its
largest difference between the decoded action and the ONNX policy on the decoded observation; the run
records no per-step values, so no ULP).
"""

from __future__ import annotations

from pathlib import Path
from typing import Any

import numpy as np

from embedrl.common import owned_temporary_folder
from embedrl.hil.node_kinds import NODE_KINDS


def links(
    export_dir: Path, export: dict[str, Any], row: dict[str, Any], hils: list[tuple[str, dict[str, Any]]]
) -> list[dict[str, Any]]:
    """One dict per link: ``source``, ``to``, ``samples``, ``max_abs``, ``max_ulp``, ``tolerance``, ``passed``
    (None: not measured, ``how`` says why) and ``how``."""
    from embedrl.hil.session import TOLERANCE as HIL_TOLERANCE

    v = export["verification"]
    tolerance = float(v["tolerance"])
    sb3 = v.get("onnx_vs_sb3_max_abs_error")
    sb3_how = "the export's figure (the report does not load the SB3 zip)"
    c_how = "recomputed by the report"
    if sb3 is None:
        sb3_how = "not measured: the export had no SB3 model"
    if row["max_error"] is None:
        c_how = f"not recomputed: {row['generated_c']}"
    rows = [
        _link("SB3 predict(deterministic=True)", "ONNX (onnxruntime)",
              v["samples"] if sb3 is not None else None, sb3, v.get("onnx_vs_sb3_max_ulp"), tolerance,
              sb3_how),
        _link("ONNX (onnxruntime)", "C on the host", row["samples"] or None, row["max_error"],
              row.get("max_ulp"), tolerance, c_how),
    ]  # fmt: skip
    for target in export.get("targets", {}):
        rows.append(_firmware_link(export_dir, export, row, target, tolerance))
    for name, h in hils:
        kind = NODE_KINDS.get(h["node"])
        node = (kind.where(h.get("target")) if kind else "") or f"{h['node']} node"
        diffs = [
            r["max_action_abs_diff"] for r in h["per_episode"] if r.get("max_action_abs_diff") is not None
        ]
        steps = int(h.get("steps") or 0)
        how = "the HIL run's figure: decoded action vs ONNX on the decoded observation"
        rows.append(_link(f"{node} ({name})", "action decoded from the bus", steps or None,
                          max(diffs, default=None), None, HIL_TOLERANCE, how))  # fmt: skip
    return rows


def _link(
    source: str,
    to: str,
    samples: int | None,
    max_abs: float | None,
    max_ulp: int | None,
    tolerance: float,
    how: str,
) -> dict[str, Any]:
    passed = None if max_abs is None else bool(max_abs <= tolerance)
    return {"source": source, "to": to, "samples": samples, "max_abs": max_abs, "max_ulp": max_ulp,
            "tolerance": tolerance, "passed": passed, "how": how}  # fmt: skip


def _firmware_link(
    export_dir: Path, export: dict[str, Any], row: dict[str, Any], target: str, tolerance: float
) -> dict[str, Any]:
    """The C verified on the host, built for ``target`` and run under QEMU on the export's test vectors,
    against the same C on the host, bit for bit."""
    from embedrl.export import build, verify
    from embedrl.export import target as targets
    from embedrl.export.errors import ExportError
    from embedrl.export.regenerate import OBSERVATIONS
    from embedrl.hil.signoff.facts import IDENTICAL

    source, to = "C on the host", f"C on {target} (QEMU)"
    if row["generated_c"] != IDENTICAL:
        return _link(source, to, None, None, None, tolerance, f"not run: {row['generated_c']}")
    part = targets.TARGETS.get(target)
    if part is None:
        return _link(source, to, None, None, None, tolerance, f"not run: {target} is not a known target")
    observations = np.load(export_dir / OBSERVATIONS, allow_pickle=False).astype(np.float32)
    vectors = targets.pick_test_vectors(observations, int(export["verification"]["samples_from_rollouts"]))
    try:
        with owned_temporary_folder("embedrl-b2b-") as tmp:
            work = Path(tmp)
            (work / "test_vectors.c").write_text(targets.test_vectors_source(vectors))
            out = targets.build_firmware(part, export_dir / "c", work / "test_vectors.c", work / "firmware")
            run = targets.run_qemu(part, out / "firmware.elf", len(vectors), export["action_dim"])
            build.make("lib", export_dir / "c", work / "host")
            host = build.CPolicy(work / "host" / "libpolicy.so", export["name"], export["observation_dim"],
                                 export["action_dim"])  # fmt: skip
            host.reset()
            actions, codes = host.batch(vectors)
    except ExportError as exc:
        return _link(source, to, None, None, None, tolerance, f"not run: {str(exc).strip().splitlines()[-1]}")
    if np.any(run.codes != codes):
        differ = int(np.sum(run.codes != codes))
        failed = _link(
            source, to, len(vectors), None, None, tolerance, f"return codes differ on {differ} vectors"
        )
        return {**failed, "passed": False}
    how = "measured by the report: the verified C built for the target, run under QEMU"
    return _link(source, to, len(vectors), verify.max_abs_error(run.actions, actions),
                 verify.max_ulp(run.actions, actions), tolerance, how)  # fmt: skip


def check(rows: list[dict[str, Any]]) -> tuple[bool, str]:
    """The verdict's line: every measured link within its tolerance (a link not measured says so)."""
    outside = [r for r in rows if r["passed"] is False]
    measured = [r for r in rows if r["passed"] is not None]
    if outside:
        r = outside[0]
        what = (
            r["how"] if r["max_abs"] is None else f"max |difference| {r['max_abs']:.3g} > {r['tolerance']:g}"
        )
        return False, f"{r['source']} -> {r['to']}: {what}"
    worst = max((r["max_abs"] for r in measured), default=0.0)
    return (
        True,
        f"{len(measured)} of {len(rows)} links measured, each within its tolerance (worst {worst:.3g})",
    )
