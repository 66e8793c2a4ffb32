"""Whether a HIL run passed (:func:`verdict`); its summary as the command prints it."""

from __future__ import annotations

from typing import Any


def node_count(data: dict[str, Any], name: str) -> int:
    """A counter of the nodes' last NodeStatus or NodeDiag, summed over the nodes (as the nodes sent it)."""
    nodes = data.get("nodes") or [{"status": data.get("node_status"), "diag": data.get("node_diag")}]
    return sum(int({**(n["status"] or {}), **(n["diag"] or {})}.get(name, 0)) for n in nodes)


def verdict(data: dict[str, Any], allow_faults: bool) -> dict[str, Any]:
    """Whether the run passed: no episode ended in a fault, none ended differently from the
    simulation, the node refused no policy output, and the node's actions matched the exported ONNX
    within the tolerance at every step. With ``allow_faults`` the episodes with an injected fault are
    exempt from the first two and the last, and instead every injection must have been detected by the
    node (for the classes it must detect) and its step answered or not as its class requires. A
    scheduled fault that never fired fails the run either way."""
    from embedrl.hil.session import TOLERANCE

    exempt = {row["seed"] for row in data["per_episode"] if allow_faults and row["injected"]}
    faulted = sorted(
        r["seed"] for r in data["per_episode"] if r["outcome"] == "fault" and r["seed"] not in exempt
    )
    differing = [s for s in data["outcomes_differing_from_simulation"] if s not in exempt]
    diffs = [
        r["max_action_abs_diff"]
        for r in data["per_episode"]
        if r["seed"] not in exempt and r["max_action_abs_diff"] is not None
    ]
    failures = []
    if faulted:
        failures.append(f"{len(faulted)} episode(s) ended in a fault (seeds {faulted})")
    if differing:
        failures.append(
            f"{len(differing)} episode(s) ended differently from the simulation (seeds {differing})"
        )
    refused = node_count(data, "action_faults")
    if refused:
        failures.append(
            f"the node refused {refused} policy output(s) (non-finite, outside the action range or an "
            "error status) and sent the safe action instead"
        )
    if diffs and max(diffs) > TOLERANCE:
        failures.append(
            f"the node's actions differ from the export's {data.get('precision', 'float32')} reference by "
            f"{max(diffs):.3g} > {TOLERANCE}"
        )
    for where in data.get("injections_not_fired", []):
        failures.append(f"fault {where} never fired: its episode ended before that step")
    for record in data["injections"] or []:
        where = f"{record['kind']}@{record['episode']}:{record['step']}"
        if record["detected"] is False:
            failures.append(f"fault {where} was not detected by the node ({record['detects']})")
        if not record["answered_as_expected"]:
            failures.append(f"fault {where}: the step was {'' if record['answered'] else 'not '}answered")
    return {"passed": not failures, "failures": failures, "faults_allowed": allow_faults}


MS_PER_S = 1000.0


def link_health(data: dict[str, Any], sample_time_s: float | None) -> list[tuple[str, str]]:
    """The link's health in a run (none of it fails the run: timing in a sandbox is noisy, and a retried
    or stale step was still answered correctly): the harness's retries, the nodes' stale steps and send
    failures (NodeDiag's), and the round trip's 99th percentile against the sample time."""
    p99_ms = (data.get("latency_us") or {}).get("p99", 0.0) / MS_PER_S
    above = sample_time_s is not None and p99_ms > sample_time_s * MS_PER_S
    where = "above" if above else "within"
    against = "" if sample_time_s is None else f" ({where} the {sample_time_s:g} s sample time)"
    return [
        ("retries", str(data.get("retries") or 0)),
        ("stale steps", str(node_count(data, "stale_steps"))),
        ("send failures", str(node_count(data, "send_failures"))),
        ("round trip p99", f"{p99_ms:.3g} ms{against}"),
    ]


def summary_rows(data: dict[str, Any]) -> list[tuple[str, str]]:
    """The report ``data`` as (what, value) rows: the sandbox, the outcomes beside the simulation's, the
    node's counters, the round trip, each fault class and the verdict."""
    lat = data["latency_us"]
    diff = data["max_action_abs_diff"]
    rows = [("sandbox", data["sandbox_detail"])]
    if len(data["per_node"]) > 1:
        rows += [
            (f"node {k}: episodes / successes / faults / differing", f"{n['episodes']} / {n['successes']} / "
             f"{n['faults']} / {len(n['differing_from_simulation'])}")
            for k, n in data["per_node"].items()
        ]  # fmt: skip
    if data["two_robots"]:
        pairs = data["two_robots"]
        rows.append(
            (
                "two robots: episodes / both through (HIL) / (simulation)",
                f"{pairs['episodes']} / {pairs['hil_both_through']} / {pairs['simulation_both_through']}",
            )
        )
    if data["open_loop"]:
        rows.append(("open loop (no env): episodes / faults", f"{data['episodes']} / {data['faults']}"))
    else:
        rows += [
            (
                "HIL successes / collisions / timeouts / faults",
                f"{data['successes']} / {data['collisions']} / {data['timeouts']} / {data['faults']}",
            ),
            (
                "simulation successes / collisions / timeouts",
                " / ".join(str(data["simulation"][k]) for k in ("successes", "collisions", "timeouts")),
            ),
            ("episodes ending differently", str(len(data["outcomes_differing_from_simulation"]))),
        ]
    rows += [
        (
            f"steps, max |node - {data['precision']} reference|",
            f"{data['steps']}, {'-' if diff is None else f'{diff:.3g}'}",
        ),
        ("frames tx / rx", f"{data['frames_tx']} / {data['frames_rx']}"),
        (
            "node CRC / sequence errors / watchdog timeouts",
            f"{data['crc_errors']} / {data['sequence_errors']} / {node_count(data, 'timeouts')}",
        ),
        ("node action faults (refused policy outputs)", str(node_count(data, "action_faults"))),
        ("steps the node left unanswered", str(data["rx_timeouts"])),
        ("round trip p50 / p99 / max [us]", f"{lat['p50']:.0f} / {lat['p99']:.0f} / {lat['max']:.0f}"),
        (
            "link: " + " / ".join(k for k, _ in link_health(data, data.get("sample_time_s"))),
            " / ".join(v for _, v in link_health(data, data.get("sample_time_s"))),
        ),
    ]
    if data["jitter_us"]:
        jitter = data["jitter_us"]
        rows.append(
            (
                "real time: deadline misses, period jitter std / max [us]",
                f"{data['deadline_misses']}, {jitter['std']:.0f} / {jitter['max_abs']:.0f}",
            )
        )
    for kind, row in (data["fault_catalogue"] or {}).items():
        rows.append(
            (
                f"fault {kind}: injected / detected / answered as expected",
                f"{row['injected']} / {'tolerated' if row['detected'] is None else row['detected']}"
                f" / {row['answered_as_expected']}",
            )
        )
    rows += _firmware_rows(data)
    failures = data["verdict"]["failures"]
    rows.append(("verdict", "PASS" if not failures else "FAIL: " + "; ".join(failures)))
    return rows


def _firmware_rows(data: dict[str, Any]) -> list[tuple[str, str]]:
    """The firmware node's instructions per step and its worst step on the modelled part, when known."""
    rows: list[tuple[str, str]] = []
    per_step = data.get("instructions_per_step")
    if per_step:
        rows.append(
            (
                f"firmware {data['target']}: instructions per step mean / max (frame in -> action out)",
                f"{per_step['mean']:,.0f} / {per_step['max']:,.0f} over {per_step['steps']} steps",
            )
        )
    stack = (data.get("firmware") or {}).get("stack_bound")
    if stack:
        peak = data["firmware"]["stack_peak_bytes"]
        rows.append(
            (
                f"firmware {data['target']}: stack measured peak / static bound [B]",
                f"{'-' if peak is None else peak} / {stack['bytes']}",
            )
        )
    timed = data.get("time_on_target")
    if timed:
        rows.append(
            (
                f"firmware worst step on {timed['clock']['part']} (est.)",
                f"{timed['estimated_step_us']:,.0f} us, {100 * timed['fraction_of_sample_time']:.2g}% of the "
                f"{timed['sample_time_s']} s sample time (margin {timed['margin_s'] * 1000:,.1f} ms)",
            )
        )
    return rows
