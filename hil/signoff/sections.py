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
        + _back_to_back(facts["back_to_back"])
    )  # fmt: skip


def _back_to_back(links: list[dict[str, Any]]) -> str:
    rows = [
        [cell(f"{r['source']} -> {r['to']}"), cell(r["samples"]), cell(r["max_abs"], f"b2b-abs-{n}"),
         cell(r["max_ulp"], f"b2b-ulp-{n}"), cell(r["tolerance"]), cell(r["passed"], f"b2b-passed-{n}"),
         cell(r["how"])]
        for n, r in enumerate(links, 1)
    ]  # fmt: skip
    return (
        '<h3 id="back-to-back">Back to back, from the trained model to the bus</h3><p class="note">Each link '
        "compares the action at its two ends on the same observations: the largest absolute difference, and "
        "the largest distance in float32 steps (ULP; 0 is bit for bit). The bus carries each action as a "
        "fixed-point signal, and a HIL run records only its largest difference per episode: no ULP there.</p>"
        + table(["link", "samples", "max |difference|", "max ULP", "tolerance", "within", "how"], rows)
    )


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
    parts.append(cycle_model(facts))
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


def _log_count(deviation: dict[str, Any]) -> str:
    """A deviation's count for this export, or what it explains here if it is one that takes none."""
    if deviation["count"] is not None:
        return str(deviation["count"])
    return f"{deviation.get('found', 0)} here (not counted: grows with the network or the interface)"


def coding_standard(facts: dict[str, Any]) -> str:
    c = facts["coding_standard"]
    unexplained = c["unexplained"]
    per_rule: dict[str, list[str]] = {}
    for r in c["by_rule_and_file"]:
        per_rule.setdefault(r["rule"], []).append(f"{r['file']} ({r['count']})")
    category = c.get("categories", {})
    rows = [[cell(rule), cell(_category(category.get(rule))),
             cell(sum(int(f.rsplit("(", 1)[1][:-1]) for f in files)), cell(", ".join(files))]
            for rule, files in sorted(per_rule.items(), key=lambda item: _rule_order(item[0]))]  # fmt: skip
    log = [
        [cell(d["rule"]), cell(", ".join(d["files"])),
         cell(_log_count(d)), cell(d["why"])]
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
        + _configurations(c)
        + "<h3>Findings by rule</h3>" + CATEGORY_NOTE
        + table(["rule", "category", "findings", "files (findings)"], rows)
        + "<h3>Findings by file and line</h3>" + _findings_at(c)
        + "<h3>Deviation log</h3>" + table(["rule", "files", "findings allowed", "why"], log)
    )  # fmt: skip


def _configurations(c: dict[str, Any]) -> str:
    """The configurations analysed: each one's macros and how many findings occur in it."""
    analysed = c.get("configurations", [])
    names = ", ".join(a["name"] for a in analysed)
    rows = [
        [cell(a["name"]), cell(" ".join(f"-D{d}" for d in a["defines"]) or "-"),
         cell(a["compiler"] or "none of a compiler's (the standard C forms)"), cell(a["findings"])]
        for a in analysed
    ]  # fmt: skip
    return (
        "<h3>Configurations analysed</h3><p>The program is analysed once per configuration it is built for "
        "(cppcheck's <code>-D</code>), a target's with the macros its compiler predefines for its flags; "
        "each finding is listed once, with the configurations it occurs in where not all: "
        f'<span data-key="misra-configurations">{escape(names)}</span>.</p>'
        + table(["configuration", "macros", "predefined by", "findings in it"], rows)
    )


CATEGORY_NOTE = (
    '<p class="note">Category of each rule in MISRA C:2012 (the deviation log\'s <b>(A)</b> and <b>(R)</b>): '
    "<b>(A) advisory</b>, a recommendation that may be deviated with a recorded reason; <b>(R) required</b>, "
    "to be followed unless a formal deviation (the log's entry, with its justification) is recorded; "
    "<b>(M) mandatory</b>, never deviated. A cppcheck check of its own has no category.</p>"
)


def _category(category: str | None) -> str:
    return f"({category[0].upper()}) {category}" if category else "- (cppcheck)"


def _findings_at(c: dict[str, Any]) -> str:
    """Every finding as file:line, one collapsible block per rule (HTML ``details``: no script)."""
    every = [a["name"] for a in c.get("configurations", [])]
    per_rule: dict[str, list[str]] = {}
    for f in c.get("at", []):
        where = f.get("configurations", every)
        only = f" ({', '.join(where)} only)" if where != every else ""
        per_rule.setdefault(f["rule"], []).append(f"{f['file']}:{f['line']}{only}")
    blocks = []
    for rule, places in sorted(per_rule.items(), key=lambda item: _rule_order(item[0])):
        category = _category(c.get("categories", {}).get(rule))
        items = "".join(f"<li><code>{escape(p)}</code></li>" for p in places)
        blocks.append(
            f'<details data-rule="{escape(rule)}"><summary>rule {escape(rule)}, {escape(category)}: '
            f'<span data-key="misra-at-{escape(rule)}">{len(places)}</span> finding(s)</summary>'
            f'<ul class="places">{items}</ul></details>'
        )
    return "".join(blocks)


def _rule_order(rule: str) -> tuple[int, ...]:
    """MISRA rules in numeric order (2.5 before 10.1), cppcheck's own checks after them."""
    parts = rule.split(".")
    return tuple(int(p) for p in parts) if all(p.isdigit() for p in parts) else (999,)


OUTSIDE = " (outside the bundle, digest only)"


def coverage(facts: dict[str, Any]) -> str:
    """Lines, branches and MC/DC conditions per file against the goal, then every gap with its reason."""
    from embedrl.hil.signoff.coverage import GOAL_MCDC, LABELS, merged_from, shown

    c = facts["coverage"]
    if isinstance(c, str):
        return f'<p><span class="fail" data-key="coverage">not measured</span>: {escape(c)}</p>'
    rows = [
        [cell(f["file"]), cell(f["role"]), *(cell(shown(f[k]), f"coverage-{f['file']}-{k}") for k in LABELS),
         cell(f["meets_goal"] if f["in_goal"] else None), cell(len(f["gaps"]) if f["in_goal"] else None)]
        for f in c["files"]
    ]  # fmt: skip
    gaps = [
        [cell(f"{f['file']}:{g['line']}"), cell(g["kind"]), cell(g["code"]), cell(g["detail"]),
         cell(g["reason"] or "NO REASON RECORDED")]
        for f in c["files"] for g in f["gaps"]
    ]  # fmt: skip
    p = c["probes"]
    codes = ", ".join(f"code {k}: {n:,}" for k, n in p["codes"].items())
    return (
        "<p>clang's source-based coverage (<code>make -C runtime_c coverage</code>: "
        f"{escape(c['compiler']['version'])}, "
        "<code>-fprofile-instr-generate -fcoverage-mapping -fcoverage-mcdc</code>, llvm-cov-19 export; the "
        "flags in full under measurement conditions). The "
        f"policy ran on {p['verification_rows']:,} verification observations and "
        f"{p['rows'] - p['verification_rows']} probes (NaN, +/-inf, +/-1e4, +/-FLT_MAX at each position; "
        f"every position at FLT_MAX with equal and alternating signs): {codes}. "
        "The node's files ran under their C unit tests (runtime_c/tests: fake transport, clock and policy; "
        "the static scenario's CAN code) and, for each HIL report made with <code>embedrl hil run "
        "--coverage</code>, as the instrumented node in the sandbox (one raw profile per node process that "
        "exited; one killed by SIGKILL writes none). "
        f'<span data-key="coverage-sources">Profiles {escape(merged_from(c))}.</span> '
        f"Goal per file: every line, every branch both ways, MC/DC >= {GOAL_MCDC:g}% of "
        "the conditions of decisions with two or more (single-condition decisions are branches). Gaps need "
        "a reason in <code>runtime_c/coverage_reasons.toml</code>.</p>"
        + table(["file", "what", "lines", "branches", "MC/DC conditions", "meets goal", "gaps"], rows)
        + (
            f"<h3>Gaps ({len(gaps)})</h3>" + table(["where", "kind", "code", "what", "reason"], gaps)
            if gaps
            else ""
        )
    )


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


def conditions(facts: dict[str, Any]) -> str:
    """The compilers and flags per target, the tools, and the command, date and commit of each artefact."""
    c = facts["conditions"]
    compilers = [
        [cell(r["target"]), cell(r["version"] or f"not recorded ({r.get('again', 'export again')})",
                                 f"compiler-{r.get('key', r['target'])}"), cell(r["command"] or "-")]
        for r in c["compilers"]
    ]  # fmt: skip
    made = [
        [cell(r["artefact"]), cell(r["command"] or "not recorded"), cell(r["date"] or "not recorded"),
         cell(r["commit"] or "not recorded", f"commit-{n}")]
        for n, r in enumerate(c["made"])
    ]  # fmt: skip
    return (
        f'<p>Made with <b data-key="embedrl-version">{escape(c["tool"])}</b>; MISRA checked with '
        f"{escape(c['coding_tool'])}. Every figure below was measured with the compilers and flags of this "
        "table (the host library for the numerical verification, each Cortex-M image for the target "
        "figures, clang's coverage builds for the coverage).</p>"
        + table(["target", "compiler", "flags"], compilers)
        + "<h3>What made each artefact</h3><p class=\"note\">The commit is embedrl's source; \"modified "
        "files\": the checkout differed from it.</p>"
        + table(["artefact", "command", "date (UTC)", "embedrl commit"], made)
    )  # fmt: skip


def entry_points(facts: dict[str, Any]) -> str:
    """The deployed program's functions in the order they are called."""
    rows = [
        [cell(r["order"]), cell(r["prototype"], f"entry-{r['function']}"), cell(r["header"]),
         cell(r["when"] or "not described"), cell(r["what"] or "-")]
        for r in facts["entry_points"]
    ]  # fmt: skip
    name = facts["export"]["name"]
    return (
        f"<p>The firmware node (<code>runtime_c/cortex_m/node_main.c</code>) calls the node's functions, and "
        f"the node calls the policy's. Integrating <code>{escape(name)}</code> without the node: "
        f"<code>{escape(name)}_reset()</code> at start-up and at each episode start, then "
        f"<code>{escape(name)}_step()</code> once per sample period "
        f"({facts['interface']['sample_time_s']} s, <code>{escape(name.upper())}_SAMPLE_TIME_S</code>), one "
        "call at a time (file-scope buffers: not reentrant).</p>"
        + table(["order", "function", "declared in", "called", "does"], rows)
    )  # fmt: skip


def layers(facts: dict[str, Any]) -> str:
    """The policy layer by layer, as ST Edge AI's analyze lists it."""
    t = facts["layers"]
    targets = [x["target"] for x in facts["targets"]]
    rows = [
        [cell(r["op"]), cell(r["name"]), cell("x".join(map(str, r["input_shape"]))),
         cell("x".join(map(str, r["output_shape"]))), cell(r["macs"]), cell(r["weight_bytes"]),
         cell(r["activation_bytes"]), *(cell(r["cycles"][x]) for x in targets)]
        for r in t["rows"]
    ]  # fmt: skip
    total = [
        cell("total"), cell(""), cell(""), cell(""),
        cell(sum(r["macs"] for r in t["rows"]), "layers-macs"),
        cell(t["weight_bytes"], "layers-weight-bytes"),
        cell(sum(r["activation_bytes"] for r in t["rows"])),
        *(cell(next(x["measured"]["estimated_cycles_per_inference"] for x in facts["targets"]
                    if x["target"] == name)) for name in targets),
    ]  # fmt: skip
    header = t["header_weight_bytes"]
    agrees = header == t["weight_bytes"]
    check = (
        f'<span class="{"ok" if agrees else "fail"}" data-key="layers-header-agrees">'
        f"{'agrees' if agrees else 'differs'}</span> with the generated header's own count ({header} bytes)"
    )
    named = t["unattributed_bytes"]
    unattributed = f"; {named} bytes of constants are named after no layer" if named else ""
    return (
        "<p>Each node of the export's ONNX as the generator sees it (<code>policy.onnx</code> through "
        "<code>to_ir</code>). MACs: multiply-accumulates per inference. Weight bytes: the <code>static "
        "const</code> arrays of the generated C, each counted under the layer it is named after; their sum "
        f"{check}{unattributed}. Activation RAM: the layer's float32 output (an alias such as Identity has "
        "none); the generated C reuses buffers, so the policy's RAM is less than the column's sum (the "
        "target table below). Estimated cycles: each target's estimate for the whole inference "
        "apportioned by MACs (an element-wise op: one per output element); library calls such as "
        "<code>tanhf</code> cost more than that, so read the column as the weight of each layer, not a "
        "per-layer measurement.</p>"
        + table(["op", "layer", "input", "output", "MACs", "weight bytes", "activation RAM [B]",
                 *(f"est. cycles {x}" for x in targets)], [*rows, total])
    )  # fmt: skip


def cycle_model(facts: dict[str, Any]) -> str:
    """What the cycle estimate assumes, and each target's clock and instruction timings."""
    from embedrl.export.cycles import ASSUMPTIONS

    assumptions = [
        [cell(topic), cell(text, f"cycle-model-{topic.replace(' ', '-')}")] for topic, text in ASSUMPTIONS
    ]
    models = [
        [cell(t["target"]), cell(t["measured"]["clock"]["part"]),
         cell(t["measured"]["clock"]["hz"] / 1e6, f"clock-mhz-{t['target']}"),
         cell(t["measured"]["cycle_model"]["cycles_per_instruction"]),
         cell(t["measured"]["cycle_model"]["source"])]
        for t in facts["targets"]
    ]  # fmt: skip
    return (
        "<h3>Cycle model: what the estimate assumes</h3>"
        + table(["", "assumed"], assumptions)
        + table(["target", "part", "clock [MHz]", "cycles per instruction (traced)", "timings from"], models)
    )
