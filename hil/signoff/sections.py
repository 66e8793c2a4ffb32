"""Each section of the deployment report: the gathered facts made into rows and values, rendered by the
section's template (``templates/<section>.html``, autoescaped) as markup for the page."""

from __future__ import annotations

from typing import Any

from markupsafe import Markup

from embedrl.hil.signoff.page import cell, fragment, svg


def interface(facts: dict[str, Any]) -> Markup:
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
    return fragment("interface.html", i=i, fields=fields, actions=actions, frames=frames)


def _plain(text: str) -> str:
    """A docstring-style description as plain text (no reStructuredText literals)."""
    return text.replace("``", "")


def verdict(facts: dict[str, Any]) -> Markup:
    """The page's first block: PASS or FAIL, one line per check, then the warnings (what was not checked)."""
    v = facts["verdict"]
    rows = [
        [cell(c["check"]), cell(c["passed"], f"check-{c['check']}"), cell(c["detail"])] for c in v["checks"]
    ]
    return fragment("verdict.html", passed=v["passed"], rows=rows, warnings=v.get("warnings", []))


def verification(facts: dict[str, Any]) -> Markup:
    rows = [
        [cell(v["precision"], f"precision-{v['precision']}"), cell(v["generated_c"]), cell(v["samples"]),
         cell(v["max_error"], f"max-error-{v['precision']}"), cell(v["p99_error"]),
         cell(v["bit_exact_with_model"]), cell(v["passed"], f"passed-{v['precision']}"),
         cell(v["onnx_vs_source"])]
        for v in facts["verification"]
    ]  # fmt: skip
    links = [
        [cell(f"{r['source']} -> {r['to']}"), cell(r["samples"]), cell(r["max_abs"], f"b2b-abs-{n}"),
         cell(r["max_ulp"], f"b2b-ulp-{n}"), cell(r["tolerance"]), cell(r["passed"], f"b2b-passed-{n}"),
         cell(r["how"])]
        for n, r in enumerate(facts["back_to_back"], 1)
    ]  # fmt: skip
    return fragment("verification.html", rows=rows, links=links, figure=svg(facts["figures"]["errors"]))


def closed_loop(facts: dict[str, Any]) -> Markup:
    rows = [
        [cell(r["platform"]), cell(r["seed"]), cell(r.get("success")), cell(r["collisions"]),
         cell(r["timeouts"]), cell(r["verdict"]), cell(r.get("matches_simulation")),
         cell(r.get("meets_sample_time")), cell(r.get("task_succeeds")), cell(r.get("where"))]
        for r in facts["closed_loop"]
    ]  # fmt: skip
    return fragment(
        "closed_loop.html",
        rows=rows,
        any_hil=bool(facts["hil_reports"]),
        figure=svg(facts["figures"]["closed_loop"]),
    )


def resources(facts: dict[str, Any]) -> Markup:
    from embedrl.export.cycles import ASSUMPTIONS

    targets = facts["targets"]
    if not targets:
        return fragment("resources.html", targets=[])
    assumptions = [
        [cell(topic), cell(text, f"cycle-model-{topic.replace(' ', '-')}")] for topic, text in ASSUMPTIONS
    ]
    models = [
        [cell(t["target"]), cell(t["measured"]["clock"]["part"]),
         cell(t["measured"]["clock"]["hz"] / 1e6, f"clock-mhz-{t['target']}"),
         cell(t["measured"]["cycle_model"]["cycles_per_instruction"]),
         cell(t["measured"]["cycle_model"]["source"])]
        for t in targets
    ]  # fmt: skip
    memory = [
        {
            "target": t["target"],
            "path": " -> ".join(t["measured"]["node_firmware"]["stack_bound"]["main"]["deepest_path"]),
            "images": [
                {
                    "name": image,
                    "sections": [[cell(name), cell(size)] for name, size in m["sections"].items()],
                    "symbols": [[cell(s["symbol"]), cell(s["kind"]), cell(s["bytes"])] for s in m["symbols"]],
                }
                for image, m in t["images"].items()
            ],
        }
        for t in targets
    ]
    return fragment(
        "resources.html",
        targets=targets,
        summary=_target_summary(targets),
        without_node=any(t["node_step"] is None for t in targets),
        figure=svg(facts["figures"]["stack_and_memory"]),
        assumptions=assumptions,
        models=models,
        memory=memory,
    )


def _target_summary(targets: list[dict[str, Any]]) -> list[list[Any]]:
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
    return rows


def _log_count(deviation: dict[str, Any]) -> str:
    """A deviation's count for this export, or what it explains here if it is one that takes none."""
    if deviation["count"] is not None:
        return str(deviation["count"])
    return f"{deviation.get('found', 0)} here (not counted: grows with the network or the interface)"


def coding_standard(facts: dict[str, Any]) -> Markup:
    c = facts["coding_standard"]
    per_rule: dict[str, list[str]] = {}
    for r in c["by_rule_and_file"]:
        per_rule.setdefault(r["rule"], []).append(f"{r['file']} ({r['count']})")
    category = c.get("categories", {})
    ordered = sorted(per_rule.items(), key=lambda item: _rule_order(item[0]))
    by_rule = [[cell(rule), cell(_category(category.get(rule))),
                cell(sum(int(f.rsplit("(", 1)[1][:-1]) for f in files)), cell(", ".join(files))]
               for rule, files in ordered]  # fmt: skip
    log = [
        [cell(d["rule"]), cell(", ".join(d["files"])), cell(_log_count(d)), cell(d["why"])]
        for d in sorted(c["deviations"], key=lambda d: _rule_order(d["rule"]))
    ]
    analysed = c.get("configurations", [])
    configurations = [
        [cell(a["name"]), cell(" ".join(f"-D{d}" for d in a["defines"]) or "-"),
         cell(a["compiler"] or "none of a compiler's (the standard C forms)"), cell(a["findings"])]
        for a in analysed
    ]  # fmt: skip
    return fragment(
        "coding_standard.html",
        c=c,
        unexplained=c["unexplained"],
        warnings=facts["warnings"],
        configuration_names=", ".join(a["name"] for a in analysed),
        configurations=configurations,
        by_rule=by_rule,
        blocks=_findings_at(c),
        log=log,
    )


def _category(category: str | None) -> str:
    return f"({category[0].upper()}) {category}" if category else "- (cppcheck)"


def _findings_at(c: dict[str, Any]) -> list[dict[str, Any]]:
    """Every finding as file:line, one collapsible block per rule (HTML ``details``: no script)."""
    every = [a["name"] for a in c.get("configurations", [])]
    per_rule: dict[str, list[str]] = {}
    for f in c.get("at", []):
        where = f.get("configurations", every)
        only = f" ({', '.join(where)} only)" if where != every else ""
        per_rule.setdefault(f["rule"], []).append(f"{f['file']}:{f['line']}{only}")
    return [
        {"rule": rule, "category": _category(c.get("categories", {}).get(rule)), "places": places}
        for rule, places in sorted(per_rule.items(), key=lambda item: _rule_order(item[0]))
    ]


def _rule_order(rule: str) -> tuple[int, ...]:
    """MISRA rules in numeric order (2.5 before 10.1), cppcheck's own checks after them."""
    parts = rule.split(".")
    return tuple(int(p) for p in parts) if all(p.isdigit() for p in parts) else (999,)


OUTSIDE = " (outside the bundle, digest only)"


def coverage(facts: dict[str, Any]) -> Markup:
    """Lines, branches and MC/DC conditions per file against the goal, then every gap with its reason."""
    from embedrl.hil.signoff.coverage import GOAL_MCDC, LABELS, merged_from, shown

    c = facts["coverage"]
    if isinstance(c, str):
        return fragment("coverage.html", missing=c)
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
    return fragment(
        "coverage.html",
        missing=None,
        compiler=c["compiler"]["version"],
        verification_rows=int(p["verification_rows"]),
        probes=int(p["rows"]) - int(p["verification_rows"]),
        codes=", ".join(f"code {k}: {n:,}" for k, n in p["codes"].items()),
        merged=merged_from(c),
        goal=f"{GOAL_MCDC:g}",
        rows=rows,
        gaps=gaps,
    )


def traceability(facts: dict[str, Any]) -> Markup:
    rows = [
        [cell(n), cell(c["name"]), cell(c["path"] + ("" if c["in_bundle"] else OUTSIDE)),
         cell(c["sha256"][:16] + "..."), cell(", ".join(c["made_from"]) or "-"),
         cell(c["ok"], f"chain-link-{n}")]
        for n, c in enumerate(facts["chain"], 1)
    ]  # fmt: skip
    signature = facts["signature"]
    return fragment(
        "traceability.html",
        rows=rows,
        export_dir=facts["export_dir"],
        intact=all(c["ok"] for c in facts["chain"]),
        signature=signature["detail"],
        signature_class={"valid": "ok", "invalid": "fail"}.get(signature["state"], "warn"),
    )


def conditions(facts: dict[str, Any]) -> Markup:
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
    return fragment("conditions.html", c=c, compilers=compilers, made=made)


def entry_points(facts: dict[str, Any]) -> Markup:
    """The deployed program's functions in the order they are called."""
    rows = [
        [cell(r["order"]), cell(r["prototype"], f"entry-{r['function']}"), cell(r["header"]),
         cell(r["when"] or "not described"), cell(r["what"] or "-")]
        for r in facts["entry_points"]
    ]  # fmt: skip
    return fragment(
        "entry_points.html",
        name=facts["export"]["name"],
        sample_time_s=facts["interface"]["sample_time_s"],
        rows=rows,
    )


def layers(facts: dict[str, Any]) -> Markup:
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
    headers = ["op", "layer", "input", "output", "MACs", "weight bytes", "activation RAM [B]",
               *(f"est. cycles {x}" for x in targets)]  # fmt: skip
    return fragment(
        "layers.html",
        agrees=t["header_weight_bytes"] == t["weight_bytes"],
        header=t["header_weight_bytes"],
        unattributed=t["unattributed_bytes"],
        headers=headers,
        rows=[*rows, total],
    )
