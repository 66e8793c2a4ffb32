"""The report's verdict: one line per check, each from a figure the report recomputed or read from bytes
the chain covers, and PASS only when every line passes (``embedrl report`` then exits 0, else 1)."""

from __future__ import annotations

from typing import Any

from embedrl.export.target import TARGETS
from embedrl.hil.signoff import back_to_back, coverage
from embedrl.hil.verdict import link_health

FLASH_SECTIONS = (".isr_vector", ".text", ".ARM.exidx", ".data")
"""What an image puts in flash (.data's initial values included)."""
RAM_SECTIONS = (".data", ".bss", ".heap", ".stack")
KIB = 1024


def verdict(data: dict[str, Any], hils: list[tuple[str, dict[str, Any]]]) -> dict[str, Any]:
    """``{"passed": bool, "checks": [{"check", "passed", "detail"}, ...]}`` for the gathered facts."""
    checks = [_numerics(v, data["tolerance"]) for v in data["verification"]]
    checks += [_hil(name, h, data["interface"]["sample_time_s"]) for name, h in hils]
    for t in data["targets"]:
        checks += [_resources(t), _stack(t)]
    unexplained = len(data["coding_standard"]["unexplained"])
    analysed = ", ".join(c["name"] for c in data["coding_standard"].get("configurations", []))
    misra = f"{unexplained} finding(s) without a deviation" + (f" (analysed: {analysed})" if analysed else "")
    checks.append(_row("MISRA C:2012", unexplained == 0, misra))
    broken = [c for c in data["chain"] if not c["ok"]]
    outside = [c["name"] for c in data["chain"] if not c["in_bundle"]]
    checks.append(
        _row(
            "traceability chain",
            not broken,
            f"{len(data['chain'])} links intact"
            + (f" ({', '.join(outside)}: outside the bundle, digest only)" if outside else "")
            if not broken
            else f"{len(broken)} link(s) broken, first: {broken[0]['name']}: {broken[0]['detail']}",
        )
    )
    warnings = []
    signature = data["signature"]
    if signature["state"] in ("valid", "invalid"):  # checked against the user's key: a line of the verdict
        checks.append(_row("signature", signature["state"] == "valid", signature["detail"]))
    else:  # not signed, or no key to check it with: said plainly, never a PASS line
        warnings.append(f"signature: {signature['detail']}")
    checks.append(_row("coverage", *coverage.check(data["coverage"])))
    checks.append(_row("back-to-back", *back_to_back.check(data["back_to_back"])))
    return {"passed": all(c["passed"] for c in checks), "checks": checks, "warnings": warnings}


def _row(check: str, passed: bool, detail: str) -> dict[str, Any]:
    return {"check": check, "passed": bool(passed), "detail": detail}


def _numerics(v: dict[str, Any], tolerance: float) -> dict[str, Any]:
    name = f"numerics, {v['precision']}"
    if v["max_error"] is None:
        return _row(name, False, f"not recomputed: {v['generated_c']}")
    if v["bit_exact_with_model"] is not None:
        detail = (
            f"C bit-exact with its integer model on {v['samples']:,} samples"
            if v["bit_exact_with_model"]
            else f"C differs from its integer model on the {v['samples']:,} samples"
        )
        return _row(name, v["passed"], f"{detail}; max |C - policy.onnx| {v['max_error']:.3g}")
    detail = f"max |C - ONNX| {v['max_error']:.3g} on {v['samples']:,} samples (tolerance {tolerance:g})"
    return _row(name, v["passed"], detail)


def _hil(name: str, h: dict[str, Any], sample_time_s: float) -> dict[str, Any]:
    """A HIL report's own verdict, with the link's health beside it (not a verdict of its own: timing in a
    sandbox is noisy), so a passing run that needed retries says so."""
    where = f"HIL, {h['node']} node" + (f" on {h['target']}" if h.get("target") else "") + f" ({name})"
    health = ", ".join(f"{k} {v}" for k, v in link_health(h, sample_time_s))
    failures = h["verdict"].get("failures") or []
    verdict = "passed" if h["verdict"]["passed"] else "failed: " + "; ".join(str(f) for f in failures)
    return _row(where, h["verdict"]["passed"], f"{verdict}; {health}")


def _resources(t: dict[str, Any]) -> dict[str, Any]:
    """Each linked image's flash and RAM (its sections, read from the ELF files) within the modelled part's
    memory (runtime_c/cortex_m/targets.mk)."""
    name = f"resources within the part, {t['target']}"
    part = TARGETS.get(t["target"])
    if part is None:
        return _row(name, False, f"{t['target']} is not a target of runtime_c/cortex_m/targets.mk")
    if not t["images"]:
        return _row(name, False, f"no linked image in bin/{t['target']}/ to measure (export it again)")
    over, parts = [], []
    for image, memory in t["images"].items():
        sections = memory["sections"]
        flash = sum(sections.get(s, 0) for s in FLASH_SECTIONS)
        ram = sum(sections.get(s, 0) for s in RAM_SECTIONS)
        parts.append(f"{image} flash {flash:,} B, RAM {ram:,} B")
        if flash > part.flash_kib * KIB:
            over.append(f"{image}'s flash {flash:,} B")
        if ram > part.ram_kib * KIB:
            over.append(f"{image}'s RAM {ram:,} B")
    limits = f"the part's {part.flash_kib} KiB flash and {part.ram_kib} KiB RAM ({part.part})"
    if over:
        return _row(name, False, f"{', '.join(over)} exceed {limits}")
    return _row(name, True, f"{'; '.join(parts)}, within {limits}")


def _stack(t: dict[str, Any]) -> dict[str, Any]:
    """The static stack bounds hold what was painted (policy_step in the test image; the firmware node in a
    HIL run), and the node's bound fits the stack its image reserves."""
    name = f"stack bound, {t['target']}"
    m = t["measured"]
    bound, painted = m["stack_bound"]["bytes"], m["stack_bytes"]
    node_bound, node_painted = m["node_firmware"]["stack_bound"]["bytes"], t["node_stack_peak_bytes"]
    reserved = (t["images"].get("node.elf") or {}).get("sections", {}).get(".stack")
    problems = []
    if painted > bound:
        problems.append(f"policy_step painted {painted} B above its bound {bound} B")
    if node_painted is not None and node_painted > node_bound:
        problems.append(f"the node painted {node_painted} B above its bound {node_bound} B")
    if reserved is None:
        problems.append("no node.elf to read the reserved stack from")
    elif node_bound > reserved:
        problems.append(f"the node's bound {node_bound} B exceeds the {reserved} B its image reserves")
    if problems:
        return _row(name, False, "; ".join(problems))
    node = f"node bound {node_bound} B" + ("" if node_painted is None else f" (painted {node_painted} B)")
    detail = f"policy_step painted {painted} B <= bound {bound} B; {node} <= {reserved} B reserved"
    return _row(name, True, detail)
