"""Each section of the deployment report, from the gathered facts to HTML."""

from __future__ import annotations

from html import escape
from typing import Any

from embedrl.hil.signoff.page import cell, table


def interface(facts: dict[str, Any]) -> str:
    i = facts["interface"]
    fields = [
        [
            cell(f["name"]),
            cell(_plain(f["description"])),
            cell(f["unit"] or "-"),
            cell(f["low"]),
            cell(f["high"]),
        ]
        for f in i["observation"]
    ]
    actions = [
        [cell(f["name"]), cell(_plain(f["description"])), cell(f["unit"] or "-"), cell(f["low"]),
         cell(f["high"]), cell(safe, f"safe-action-{f['name']}")]
        for f, safe in zip(i["action"], i["safe_action"], strict=True)
    ]  # fmt: skip
    frames = [
        [cell(fid), cell(name), cell(sender), cell("; ".join(parts))]
        for fid, name, sender, parts in i["frames"]
    ]
    return (
        f"<p>Scenario <b>{escape(i['name'])}</b>; sample time "
        f'<b data-key="sample-time-s">{i["sample_time_s"]}</b> s; the node\'s watchdog '
        f"{i['watchdog_ms']} ms (no valid observation this long: SAFE, the safe action).</p>"
        "<h3>Observation</h3>" + table(["field", "meaning", "unit", "low", "high"], fields)
        + "<h3>Action</h3>" + table(["field", "meaning", "unit", "low", "high", "safe action"], actions)
        + "<h3>CAN frames (node 0)</h3><p class=\"note\">Every frame carries Crc (CRC-8 over the data ID and "
        "payload) and Counter (4 bits); Step ties the frames of one step together.</p>"
        + table(["ID", "message", "sent by", "signals: name (start bit, bits, scale, range, unit)"], frames)
    )  # fmt: skip


def _plain(text: str) -> str:
    """A docstring-style description as plain text (no reStructuredText literals)."""
    return text.replace("``", "")


def verdict(facts: dict[str, Any]) -> str:
    """The page's first block: PASS or FAIL, then one line per check."""
    v = facts["verdict"]
    rows = [
        [cell(c["check"]), cell(c["passed"], f"check-{c['check']}"), cell(c["detail"])] for c in v["checks"]
    ]
    word = '<span class="ok">PASS</span>' if v["passed"] else '<span class="fail">FAIL</span>'
    return str(
        f'<section id="verdict"><h2>Verdict: <span data-key="verdict">{word}</span></h2>'
        + table(["check", "passed", "what was checked"], rows)
        + "</section>"
    )


def verification(facts: dict[str, Any]) -> str:
    rows = []
    for v in facts["verification"]:
        rows.append([
            cell(v["precision"], f"precision-{v['precision']}"), cell(v["generated_c"]), cell(v["samples"]),
            cell(v["max_error"], f"max-error-{v['precision']}"), cell(v["p99_error"]),
            cell(v["bit_exact_with_model"]), cell(v["passed"], f"passed-{v['precision']}"),
            cell(v["onnx_vs_source"]),
        ])  # fmt: skip
    return str(
        "<p>Recomputed for this page, not copied from the export's report. The C is first generated "
        "again from the export's ONNX and compared byte for byte with its <code>c/</code> folder: C that is "
        "not the generator's is never built or run here. Then it is built and run on the export's "
        "verification observations (uniform over the interface's ranges and recorded from rollouts), "
        "against the float ONNX with onnxruntime; a quantised policy's distance is its quantisation error, "
        "and its C must equal its integer model bit for bit.</p>"
        + table(["precision", "generated C", "samples", "max |C - ONNX|", "99th percentile",
                 "bit-exact with its model", "passed", "max |ONNX - source model|"], rows)
        + facts["figures"]["errors"]
    )  # fmt: skip


def closed_loop(facts: dict[str, Any]) -> str:
    rows = [
        [cell(r["platform"]), cell(r["seed"]), cell(r["episodes"]), cell(r["successes"]),
         cell(r["collisions"]), cell(r["timeouts"]), cell(r["verdict"])]
        for r in facts["closed_loop"]
    ]  # fmt: skip
    missing = "" if facts["hil_reports"] else (
        '<p class="note">No HIL report given: add <code>--hil REPORT.json</code> (from <code>embedrl hil run '
        "--json</code>, with <code>--node firmware</code> for the processor in the loop).</p>"
    )  # fmt: skip
    return str(
        "<p>The same policy on each platform; each HIL run beside the simulation on its own seeds.</p>"
        + missing
        + table(["platform", "seed", "episodes", "successes", "collisions", "timeouts", "HIL verdict"], rows)
        + facts["figures"]["closed_loop"]
    )


def resources(facts: dict[str, Any]) -> str:
    if not facts["targets"]:
        return (
            '<p class="note">No Cortex-M target in this export: export with <code>--target cortex-m4</code> '
            "(or m3, m7) for flash, RAM, the stack bound and the time per inference.</p>"
        )
    parts = [_target_summary(facts["targets"])]
    if any(t["node_step"] is None for t in facts["targets"]):
        parts.append(
            '<p class="note">The firmware node\'s worst step and painted stack come from <code>embedrl hil '
            "run --node firmware --target TARGET --json REPORT.json</code> given with <code>--hil</code> "
            "(the node on QEMU, closing the loop over CAN); without one, they are left out.</p>"
        )
    parts.append(facts["figures"]["stack_and_memory"])
    for t in facts["targets"]:
        parts.append(_memory_tables(t))
    return "".join(parts)


def _target_summary(targets: list[dict[str, Any]]) -> str:
    rows = []
    for t in targets:
        m, name = t["measured"], t["target"]
        node = m["node_firmware"]
        step = t["node_step"]
        rows.append([
            cell(name), cell(m["clock"]["part"]), cell(m["flash_bytes"], f"policy-flash-{name}"),
            cell(m["ram_bytes"]), cell(m["stack_bytes"], f"stack-painted-{name}"),
            cell(m["stack_bound"]["bytes"], f"stack-bound-{name}"),
            cell(node["stack_bound"]["bytes"], f"node-stack-bound-{name}"),
            cell(t["node_stack_peak_bytes"], f"node-stack-painted-{name}"),
            cell(round(m["instructions_per_inference"]), f"instructions-{name}"),
            cell(m["estimated_cycles_per_inference"]),
            cell(m["estimated_inference_us"], f"inference-us-{name}"),
            cell(None if step is None else step["estimated_step_us"], f"node-step-us-{name}"),
            cell(None if step is None else round(step["margin_s"] * 1000, 1), f"margin-ms-{name}"),
            cell(None if m["fraction_of_sample_time"] is None else 100 * m["fraction_of_sample_time"],
                 f"share-of-sample-time-{name}"),
        ])  # fmt: skip
    return (
        "<p>Measured on QEMU (instructions under <code>-icount</code>, stack painted) and bounded statically "
        "(GCC's <code>-fstack-usage</code> and call graph; the library code from the linked image). Cycles "
        "are an estimate from the core's technical reference manual, at the modelled part's clock.</p>"
        + table(["target", "part", "policy flash [B]", "policy RAM [B]", "policy_step stack painted [B]",
                 "policy_step stack bound [B]", "node stack bound [B]", "node stack painted [B]",
                 "instructions per inference", "est. cycles", "est. inference [us]", "node worst step [us]",
                 "margin to the sample time [ms]",
                 "% of sample time"], rows)
    )  # fmt: skip


def _memory_tables(t: dict[str, Any]) -> str:
    out = [f"<h3>{escape(t['target'])}</h3>"]
    path = " -> ".join(t["measured"]["node_firmware"]["stack_bound"]["main"]["deepest_path"])
    out.append(f'<p class="note">Deepest call chain of the node\'s loop: <code>{escape(path)}</code>.</p>')
    for image, memory in t["images"].items():
        sections = [[cell(name), cell(size)] for name, size in memory["sections"].items()]
        symbols = [[cell(s["symbol"]), cell(s["kind"]), cell(s["bytes"])] for s in memory["symbols"]]
        out.append(
            f'<p><b>{escape(image)}</b></p><div class="pair">'
            + table(["section", "bytes"], sections)
            + table(["largest symbols", "kind", "bytes"], symbols)
            + "</div>"
        )
    return "".join(out)


def coding_standard(facts: dict[str, Any]) -> str:
    c = facts["coding_standard"]
    unexplained = c["unexplained"]
    per_rule: dict[str, list[str]] = {}
    for r in c["by_rule_and_file"]:
        per_rule.setdefault(r["rule"], []).append(f"{r['file']} ({r['count']})")
    rows = [[cell(rule), cell(sum(int(f.rsplit("(", 1)[1][:-1]) for f in files)), cell(", ".join(files))]
            for rule, files in sorted(per_rule.items(), key=lambda item: _rule_order(item[0]))]  # fmt: skip
    log = [
        [cell(d["rule"]), cell(", ".join(d["files"])),
         cell("any (generated)" if d["count"] is None else d["count"]), cell(d["why"])]
        for d in sorted(c["deviations"], key=lambda d: _rule_order(d["rule"]))
    ]  # fmt: skip
    state = (
        '<span class="ok" data-key="misra-unexplained">0</span> unexplained findings'
        if not unexplained
        else f'<span class="fail" data-key="misra-unexplained">{len(unexplained)}</span> unexplained '
        "findings: " + escape("; ".join(unexplained))
    )
    return (
        f"<p>MISRA C:2012 with {escape(c['tool'])}'s MISRA addon (rule numbers; the rule texts are not "
        "distributed) over the firmware node as deployed: "
        f"<span data-key=\"misra-findings\">{c['findings']}</span> findings, {state}. Compiler "
        f"warnings: <code>{escape(facts['warnings'])}</code> with <code>-Werror</code>: none.</p>"
        "<h3>Findings by rule</h3>" + table(["rule", "findings", "files (findings)"], rows)
        + "<h3>Deviation log</h3>" + table(["rule", "files", "findings allowed", "why"], log)
    )  # fmt: skip


def _rule_order(rule: str) -> tuple[int, ...]:
    """MISRA rules in numeric order (2.5 before 10.1), cppcheck's own checks after them."""
    parts = rule.split(".")
    return tuple(int(p) for p in parts) if all(p.isdigit() for p in parts) else (999,)


OUTSIDE = " (outside the bundle, digest only)"


def traceability(facts: dict[str, Any]) -> str:
    rows = [
        [cell(n), cell(c["name"]), cell(c["path"] + ("" if c["in_bundle"] else OUTSIDE)),
         cell(c["sha256"][:16] + "..."), cell(", ".join(c["made_from"]) or "-"),
         cell(c["ok"], f"chain-link-{n}")]
        for n, c in enumerate(facts["chain"], 1)
    ]  # fmt: skip
    intact = all(c["ok"] for c in facts["chain"])
    return (
        f"<p>Every link hashed (SHA-256), from the run to each report; <code>embedrl verify-chain "
        f"{escape(facts['export_dir'])}</code> recomputes them. Chain "
        f'<span class="{"ok" if intact else "fail"}" data-key="chain-intact">'
        f"{'intact' if intact else 'BROKEN'}</span>; signature: "
        f'<span class="{"ok" if facts["signature"]["passed"] else "fail"}" data-key="signature">'
        f"{escape(facts['signature']['detail'])}</span>.</p>"
        + table(["#", "link", "file", "sha256", "made from", "matches"], rows)
    )
