"""The report's verdict: one line per check, each from a figure the report recomputed or read from bytes
the chain covers, and PASS only when every line passes (``embedrl report`` then exits 0, else 1)."""

from __future__ import annotations

from typing import Any

MS_PER_S = 1000.0


def verdict(data: dict[str, Any], hils: list[tuple[str, dict[str, Any]]]) -> dict[str, Any]:
    """``{"passed": bool, "checks": [{"check", "passed", "detail"}, ...]}`` for the gathered facts."""
    checks = [_numerics(v, data["tolerance"]) for v in data["verification"]]
    checks += [_hil(name, h, data["interface"]["sample_time_s"]) for name, h in hils]
    unexplained = len(data["coding_standard"]["unexplained"])
    checks.append(_row("MISRA C:2012", unexplained == 0, f"{unexplained} finding(s) without a deviation"))
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
    checks.append(_row("signature", data["signature"]["passed"], data["signature"]["detail"]))
    return {"passed": all(c["passed"] for c in checks), "checks": checks}


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
        return _row(name, v["passed"], f"{detail}; max |C - float ONNX| {v['max_error']:.3g}")
    detail = f"max |C - ONNX| {v['max_error']:.3g} on {v['samples']:,} samples (tolerance {tolerance:g})"
    return _row(name, v["passed"], detail)


def _hil(name: str, h: dict[str, Any], sample_time_s: float) -> dict[str, Any]:
    """A HIL report's own verdict, with the link's health beside it (not a verdict of its own: timing in a
    sandbox is noisy), so a passing run that needed retries says so."""
    where = f"HIL, {h['node']} node" + (f" on {h['target']}" if h.get("target") else "") + f" ({name})"
    status, diag = h.get("node_status") or {}, h.get("node_diag") or {}
    p99_ms = (h.get("latency_us") or {}).get("p99", 0.0) / MS_PER_S
    health = [
        f"retries {h.get('retries', 0)}",
        f"stale steps {status.get('stale_steps', 0)}",
        f"send failures {diag.get('send_failures', 0)}",
        f"round trip p99 {p99_ms:.3g} ms"
        + (" (above the sample time)" if p99_ms > sample_time_s * MS_PER_S else ""),
    ]
    failures = h["verdict"].get("failures") or []
    verdict = "passed" if h["verdict"]["passed"] else "failed: " + "; ".join(str(f) for f in failures)
    return _row(where, h["verdict"]["passed"], f"{verdict}; {', '.join(health)}")
