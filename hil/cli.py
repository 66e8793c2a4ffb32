"""``embedrl hil run``: the exported C policy as a CAN node, driven by the simulator over vcan."""

from __future__ import annotations

import argparse
import json
import os
import shutil
import tempfile
from contextlib import nullcontext
from dataclasses import asdict
from pathlib import Path
from typing import TYPE_CHECKING, Any

from embedrl.common import parse_json
from embedrl.hil import candb
from embedrl.hil.errors import HilError
from embedrl.hil.faults import INJECT_STEP, INJECTORS, parse_schedule
from embedrl.hil.sandbox import MODES
from embedrl.train.interface import INTERFACE_FILE, NO_ENV
from embedrl.train.scenarios import TWO_ROBOTS

if TYPE_CHECKING:
    from embedrl.hil.sandbox import Guest
    from embedrl.hil.session import SessionConfig

REPO = Path(__file__).resolve().parents[1]
SESSION_TIMEOUT_S = 3600.0
"""A whole HIL session inside a guest (pure emulation runs Python about ten times slower)."""
DEFAULT_TIMEOUT_MS = candb.WATCHDOG_MS
ACTION_TIMEOUT_S = 2.0
"""How long the simulator waits for the node's answer to a step (on the host; stretched in slow guests)."""
TWO_ROBOT_NODES = 2
"""The two-robot scenario runs one node per robot."""


def _onnx_of(export_dir: Path) -> Path:
    onnx = export_dir / "policy.onnx"
    if onnx.is_file():
        return onnx
    report = export_dir / "export_report.json"
    if report.is_file():
        source = Path(parse_json(report.read_text())["source"]["path"])
        if source.suffix == ".onnx" and source.is_file():
            return source
    raise HilError(f"{export_dir}: no policy.onnx (is it an `embedrl export` folder?)")


def run_hil(args: argparse.Namespace, guest: Guest | None = None) -> dict[str, Any]:
    """Build the node, then run the session in ``guest`` (or in the sandbox ``args.sandbox`` selects).

    The temporary work folder is removed after a successful run and kept, and named, after a failure.
    """
    export_dir: Path = args.export_dir.resolve()
    if not (export_dir / "c" / "policy.c").is_file():
        raise HilError(
            f"{export_dir}: no c/policy.c (is it an `embedrl export` folder with the default --name?)"
        )
    onnx = _onnx_of(export_dir)
    if not (export_dir / INTERFACE_FILE).is_file():
        raise HilError(
            f"{export_dir}: no {INTERFACE_FILE} (the policy's interface, from which the CAN database is "
            "generated): export it again with `embedrl export`"
        )
    interface = candb.load_interface(export_dir / INTERFACE_FILE)  # untrusted: validated before use
    if args.nodes > 1 and interface.env_id == NO_ENV:
        raise HilError("a policy without an env runs in open loop on one node: drop --nodes")
    if interface.env_id == TWO_ROBOTS.env_id:  # one node per robot
        if args.nodes not in (1, TWO_ROBOT_NODES):
            raise HilError(f"the two-robot scenario runs one node per robot: drop --nodes {args.nodes}")
        args.nodes = TWO_ROBOT_NODES
        if args.inject or args.realtime:
            raise HilError(
                "the two-robot scenario runs its two nodes in lock-step: drop --inject and --realtime "
                "(--kill-node takes a node down)"
            )
    for s in parse_schedule(args.inject):
        if s.step > interface.max_steps:
            raise HilError(
                f"--inject {s.injector.name}@{s.episode}:{s.step}: episodes of {interface.name!r} end by "
                f"step {interface.max_steps}, so the fault could never fire"
            )
    if args.kill_node is not None and args.nodes < 2:
        raise HilError("--kill-node takes one of several nodes down; with one node use --inject kill")
    if args.kill_node is not None and args.kill_node[0] >= args.nodes:
        raise HilError(f"--kill-node {args.kill_node[0]}: the run has nodes 0..{args.nodes - 1}")
    period_ms = interface.sample_time_s * 1000
    if args.realtime and (args.timeout_ms or DEFAULT_TIMEOUT_MS) <= period_ms:
        raise HilError(
            f"--timeout-ms {args.timeout_ms or DEFAULT_TIMEOUT_MS} would trip the node's watchdog between "
            "real-time steps: "
            f"it must exceed the policy's sample time ({period_ms:.0f} ms)"
        )
    work = Path(tempfile.mkdtemp(prefix="embedrl-hil-"))
    try:
        results = _build_and_run(args, guest, export_dir, onnx, work)
    except HilError as exc:
        raise HilError(f"{exc} [node build and guest console kept in {work}]") from None
    except BaseException:  # interrupted (SIGINT, SIGTERM): nothing to diagnose, nothing left behind
        if not args.keep_work:
            shutil.rmtree(work, ignore_errors=True)
        raise
    if args.keep_work:
        print(f"kept the node build and guest files in {work}")
    else:
        shutil.rmtree(work, ignore_errors=True)
    return results


def _session_config(
    args: argparse.Namespace, onnx: Path, export_dir: Path, slowdown: float = 1.0, **where: Any
) -> SessionConfig:
    """The session's settings; ``slowdown`` (the guest's, :attr:`Guest.slowdown`) stretches the default
    watchdog and the wait for an answer."""
    from embedrl.export.reference import OBSERVATIONS_FILE
    from embedrl.hil.session import SessionConfig

    observations = export_dir / "test" / OBSERVATIONS_FILE
    env_id = candb.load_interface(export_dir / INTERFACE_FILE).env_id
    open_loop = env_id == NO_ENV
    if env_id == TWO_ROBOTS.env_id:
        nodes = "of two robots, one node each, "
    elif args.nodes > 1:
        nodes = f"on each of {args.nodes} nodes "
    else:
        nodes = ""
    print(
        f"running {args.episodes} episode(s) "
        + nodes
        + ("in open loop (no env)" if open_loop else "in real time" if args.realtime else "in lock-step")
        + (f", injecting {', '.join(args.inject)}" if args.inject else "")
    )
    return SessionConfig(
        onnx=str(onnx),
        export_dir=str(export_dir),
        interface=str(export_dir / INTERFACE_FILE),
        node=args.node,
        episodes=args.episodes,
        seed=args.seed,
        node_timeout_ms=round(args.timeout_ms or DEFAULT_TIMEOUT_MS * slowdown),
        action_timeout_s=ACTION_TIMEOUT_S * slowdown,
        realtime=args.realtime,
        inject=tuple(args.inject),
        nodes=args.nodes,
        kill_node=args.kill_node,
        fd=args.fd,
        observations=str(observations) if observations.is_file() else None,
        **where,
    )


def _build_and_run(
    args: argparse.Namespace, guest: Guest | None, export_dir: Path, onnx: Path, work: Path
) -> dict[str, Any]:
    from embedrl.export import build
    from embedrl.export.errors import BuildError
    from embedrl.hil import sandbox
    from embedrl.hil.session import run

    if args.node == "python":
        # The reference node on python-can's virtual bus, in this process: no kernel, no build.
        log = work / f"frames{args.log.suffix}" if args.log else None
        cfg = _session_config(
            args, onnx, export_dir, bus="virtual", iface=f"embedrl-{os.getpid()}-{work.name}",
            log=str(log) if log else None, results=str(work / "results.json"),
        )  # fmt: skip
        local = run(cfg)
        if log:
            args.log.parent.mkdir(parents=True, exist_ok=True)
            shutil.move(log, args.log)
        return {
            **local,
            "sandbox": "none",
            "sandbox_detail": "python-can virtual bus (Python reference node)",
        }

    print(f"building the node: make -C runtime_c node POLICY_DIR={export_dir / 'c'}")
    try:
        build.make("node", export_dir / "c", work / "build", extra={"FD": "1"} if args.fd else None)
    except BuildError as exc:
        raise HilError(str(exc)) from None
    with nullcontext(guest) if guest else sandbox.opened(args.sandbox, work / "sandbox") as where:
        if args.timeout_ms is None and where.slowdown > 1:
            print(
                f"node watchdog {DEFAULT_TIMEOUT_MS * where.slowdown:.0f} ms: {where.provider} runs the "
                f"simulator ~{where.slowdown:.0f}x slower than the host (--timeout-ms sets another)"
            )
        scratch = where.scratch()  # the session's results and log: writable from inside the guest
        log = scratch / f"frames{args.log.suffix}" if args.log else None
        cfg = _session_config(
            args, onnx, export_dir, node_binary=str(work / "build" / "policy_node"), iface=where.iface,
            log=str(log) if log else None, results=str(scratch / "results.json"), slowdown=where.slowdown,
        )  # fmt: skip
        config_file = scratch / "session.json"
        config_file.write_text(json.dumps(asdict(cfg)))
        job = where.run(
            [where.python, "-m", "embedrl.hil.session", str(config_file)], REPO, timeout_s=SESSION_TIMEOUT_S
        )
        if job.status != 0 or not Path(cfg.results).is_file():
            why = where.diagnose(f"the HIL session failed (status {job.status}): {job.last_lines()}")
            raise HilError(str(why))
        results: dict[str, Any] = json.loads(Path(cfg.results).read_text())
        if log:
            args.log.parent.mkdir(parents=True, exist_ok=True)
            shutil.move(log, args.log)
        results["sandbox"] = where.provider
        results["sandbox_detail"] = where.description
        shutil.rmtree(scratch, ignore_errors=True)
    return results


def _report(args: argparse.Namespace, results: dict[str, Any]) -> dict[str, Any]:
    """The evaluation report format plus the HIL keys, and the simulation on the same seeds."""
    import numpy as np

    from embedrl.train.evaluate import REPORT_KEYS, EpisodeResult, EvalReport, evaluate

    episodes = [
        EpisodeResult(
            e["seed"],
            _robot_outcome(e["outcome"]),
            e["steps"],
            e["episode_return"],
            e["time_s"],
            e.get("collided_with"),
            [tuple(p) for p in e["trajectory"]],
        )
        for e in results["episodes"]
    ]
    report = EvalReport.from_results(episodes, args.seed, f"HIL {args.export_dir}")
    from embedrl.export.reference import precision_of, reference_policy
    from embedrl.hil.nodes import action_ok

    reference = reference_policy(args.export_dir.resolve())  # the export's precision: float, int8, q15
    precision = precision_of(args.export_dir.resolve())
    interface = candb.load_interface(args.export_dir.resolve() / INTERFACE_FILE)
    safe = np.asarray(interface.safe_action, dtype=np.float32)

    def simulated(obs: np.ndarray) -> np.ndarray:
        """The export's policy in the simulation, with the node's rule: an action it would refuse is the
        safe action."""
        out = reference(obs.reshape(1, -1)).reshape(-1)
        return out if action_ok(out, interface) else safe

    pairs = None
    if interface.env_id == NO_ENV:  # open loop: no plant to simulate; the actions are compared per step
        sim = None
    elif interface.env_id == TWO_ROBOTS.env_id:  # one row per robot; the simulation drives both robots
        simulated_pairs = evaluate(
            simulated, args.episodes, args.seed, "simulation (onnxruntime)", False, interface.env_id
        ).results
        by_seed_pair = {r.seed: r for r in simulated_pairs}
        robot_rows = [
            EpisodeResult(
                h.seed,
                _robot_outcome(by_seed_pair[h.seed].robots[k]),
                h.steps,
                by_seed_pair[h.seed].robot_returns[k],
                h.time_s,
                None,
            )
            for h, k in zip(episodes, (e["node"] for e in results["episodes"]), strict=True)
        ]
        sim = EvalReport.from_results(robot_rows, args.seed, "simulation (onnxruntime)")
        hil_pairs: dict[int, list[str]] = {}
        for e in results["episodes"]:
            hil_pairs.setdefault(e["seed"], []).append(e["outcome"])
        pairs = {
            "episodes": len(hil_pairs),
            "hil_both_through": sum(o == ["success", "success"] for o in hil_pairs.values()),
            "simulation_both_through": sum(r.outcome == "success" for r in simulated_pairs),
        }
    else:  # each node's robot on its own seeds (node_seed), in the order the HIL rows have
        from embedrl.hil.session import NODE_SEED_STRIDE

        per_episode = -(-len(episodes) // args.nodes)
        by_seed = {
            r.seed: r
            for k in range(args.nodes)
            for r in evaluate(
                simulated, per_episode, args.seed + k * NODE_SEED_STRIDE, "simulation (onnxruntime)", False,
                interface.env_id, interface.sample_time_s,
            ).results
        }  # fmt: skip
        sim = EvalReport.from_results(
            [by_seed[h.seed] for h in episodes], args.seed, "simulation (onnxruntime)"
        )
    sim_results = sim.results if sim else [None] * len(episodes)
    differing = [h.seed for h, s in zip(episodes, sim_results, strict=True) if s and h.outcome != s.outcome]
    keys = (
        "steps",
        "max_action_abs_diff",
        "first_divergent_step",
        "frames_tx",
        "frames_rx",
        "crc_errors",
        "sequence_errors",
        "rx_timeouts",
        "sandbox",
        "sandbox_detail",
        "latency_us",
        "deadline_misses",
        "jitter_us",
        "node_status",
        "node_diag",
        "retries",
        "injections",
        "fault_catalogue",
        "nodes",
    )
    extra = {k: results.get(k) for k in keys}
    extra["faults"] = sum(e.outcome == "fault" for e in episodes)
    extra["simulation"] = {k: getattr(sim, k) for k in REPORT_KEYS} if sim else None
    extra["outcomes_differing_from_simulation"] = differing
    extra["max_return_abs_diff"] = (
        max(abs(h.episode_return - s.episode_return) for h, s in zip(episodes, sim.results, strict=True))
        if sim
        else None
    )
    extra["open_loop"] = sim is None
    extra["precision"] = precision  # what the node's actions were compared with
    extra["two_robots"] = pairs
    extra["can_rounding_error"] = candb.rounding_errors(interface)  # the signals' resolution, stated
    data = report.to_json(extra)
    for row, e, s in zip(data["per_episode"], results["episodes"], sim_results, strict=True):
        row["fault"] = e["fault"]
        row["simulation_return"] = s.episode_return if s else None  # lock-step: equal up to quantisation
        row["injected"] = e["injected"]
        row["max_action_abs_diff"] = e["max_action_abs_diff"]
        row["node"] = e.get("node", 0)
    data["per_node"] = {
        k: {
            "episodes": sum(r["node"] == k for r in data["per_episode"]),
            "successes": sum(r["node"] == k and r["outcome"] == "success" for r in data["per_episode"]),
            "faults": sum(r["node"] == k and r["outcome"] == "fault" for r in data["per_episode"]),
            "differing_from_simulation": [
                r["seed"] for r in data["per_episode"] if r["node"] == k and r["seed"] in differing
            ],
        }
        for k in range(args.nodes)
    }
    if args.plot:
        from embedrl.hil.plots import plot_latency
        from embedrl.train.plots import plot_trajectories

        if any(e.trajectory for e in episodes):  # envs with a map (the warehouse scenarios)
            plot_trajectories(report, args.plot / "hil_trajectories.png")
        plot_latency(
            results["latencies_us"], args.plot / "hil_latency.png", results["sandbox"], args.realtime
        )
    return data


def cmd_run(args: argparse.Namespace, guest: Guest | None = None) -> int:
    from embedrl.common import table, write_json

    if args.episodes < 1:
        raise HilError(f"--episodes must be at least 1, got {args.episodes}")
    if args.timeout_ms is not None and not 1 <= args.timeout_ms <= 60_000:
        raise HilError(f"--timeout-ms must be within 1..60000, got {args.timeout_ms}")
    try:
        schedule = parse_schedule(args.inject)
    except ValueError as exc:
        raise HilError(str(exc)) from None
    if not 1 <= args.nodes <= candb.MAX_NODES:
        raise HilError(f"--nodes must be within 1..{candb.MAX_NODES}, got {args.nodes}")
    if args.nodes > 1 and (schedule or args.realtime):
        raise HilError("--nodes > 1 runs in lock-step without fault injection: drop --inject and --realtime")
    if args.kill_node is not None and args.kill_node[1] >= args.episodes:
        raise HilError(
            f"--kill-node {args.kill_node[0]}@{args.kill_node[1]}:{args.kill_node[2]}: the run has "
            f"{args.episodes} episode(s)"
        )
    for s in schedule:
        if s.episode >= args.episodes:
            raise HilError(
                f"--inject {s.injector.name}@{s.episode}:{s.step}: the run has {args.episodes} episode(s)"
            )
        if s.injector.needs_socketcan and args.node == "python":
            raise HilError(f"--inject {s.injector.name} acts on the kernel's CAN interface: use --node c")
    if schedule and not args.allow_faults:
        print("note: injected faults change their episodes; without --allow-faults the run fails")
    results = run_hil(args, guest)
    data = _report(args, results)
    fired = {(r["kind"], r["episode"], r["step"]) for r in data["injections"] or []}
    data["injections_not_fired"] = [
        f"{s.injector.name}@{s.episode}:{s.step}"
        for s in schedule
        if (s.injector.name, s.episode, s.step) not in fired
    ]
    data["verdict"] = verdict(data, args.allow_faults)
    lat = data["latency_us"]
    diff = data["max_action_abs_diff"]
    rows = [("sandbox", data["sandbox_detail"])]
    if args.nodes > 1:
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
            f"{data['crc_errors']} / {data['sequence_errors']} / {_node_count(data, 'timeouts')}",
        ),
        ("node action faults (refused policy outputs)", str(_node_count(data, "action_faults"))),
        ("steps the node left unanswered", str(data["rx_timeouts"])),
        ("round trip p50 / p99 / max [us]", f"{lat['p50']:.0f} / {lat['p99']:.0f} / {lat['max']:.0f}"),
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
    failures = data["verdict"]["failures"]
    rows.append(("verdict", "PASS" if not failures else "FAIL: " + "; ".join(failures)))
    print(table(rows))
    written = [str(p) for p in (args.json, args.log, args.plot) if p]
    if args.json:
        write_json(data, args.json)
    if written:
        print(f"wrote {', '.join(written)}")
    return 0 if not failures else 1


def _node_count(data: dict[str, Any], name: str) -> int:
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
    refused = _node_count(data, "action_faults")
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


def _robot_outcome(outcome: str) -> str:
    """A robot's outcome in the report's terms: ``stopped`` (the other robot crashed) counts as a timeout."""
    return "timeout" if outcome == "stopped" else outcome


def _kill_spec(text: str) -> tuple[int, int, int]:
    node, at, rest = text.partition("@")
    episode, colon, step = rest.partition(":")
    try:
        values = (int(node), int(episode), int(step))
    except ValueError:
        values = (-1, -1, -1)
    if not at or not colon or min(values) < 0:
        raise argparse.ArgumentTypeError(f"expected NODE@EPISODE:STEP (numbers >= 0), got {text!r}")
    return values


def cmd_doctor(args: argparse.Namespace) -> int:
    from embedrl.common import write_json
    from embedrl.hil.doctor import doctor, print_table

    report = doctor(say=print, mode=args.sandbox)
    print_table(report)
    if args.json:
        write_json(report, args.json)
        print(f"wrote {args.json}")
    return 0 if report["first_working"] else 1


def register(sub: Any) -> None:
    p = sub.add_parser("hil", help="hardware-in-the-loop over virtual SocketCAN")
    hil_sub = p.add_subparsers(dest="hil_command", required=True, metavar="COMMAND")
    r = hil_sub.add_parser("run", help="run episodes with the exported C policy as a CAN node")
    r.add_argument("--export-dir", type=Path, required=True, help="an `embedrl export` folder")
    r.add_argument("--episodes", type=int, default=10)
    r.add_argument("--seed", type=int, default=0)
    r.add_argument(
        "--realtime", action="store_true", help="pace at the env's sample time (a report, not a verdict)"
    )
    r.add_argument("--log", type=Path, help="write every frame here (candump format, .log; .blf also works)")
    r.add_argument("--json", type=Path, help="write the report here")
    r.add_argument("--plot", type=Path, help="write trajectories and the latency histogram into this folder")
    r.add_argument(
        "--sandbox",
        choices=MODES,
        default="auto",
        help="where vcan0 comes from (auto: the first of host, uml, qemu that passes its self-test)",
    )
    r.add_argument(
        "--timeout-ms",
        type=int,
        help=f"the node's watchdog (default {candb.WATCHDOG_MS}, times the sandbox's slowdown: 10 under QEMU "
        "emulation); must exceed the policy's sample time",
    )
    r.add_argument(
        "--inject",
        action="append",
        default=[],
        metavar="FAULT[@EPISODE:STEP]",
        help=f"inject a fault (repeatable; default at step {INJECT_STEP} of episode 0): "
        + ", ".join(INJECTORS),
    )
    r.add_argument(
        "--allow-faults",
        action="store_true",
        help="pass even if episodes end in a fault (fault-injection runs); by default a fault fails the run",
    )
    r.add_argument("--keep-work", action="store_true", help="keep the temporary node build and guest files")
    r.add_argument(
        "--fd",
        action="store_true",
        help="observation and action frames in CAN FD (64 bytes, 24 values each; vcan carries them)",
    )
    r.add_argument(
        "--nodes",
        type=int,
        default=1,
        help="nodes on one bus, one robot each with its own seeds (policy_node --node-id 0..N-1), lock-step; "
        "a two-robot export always runs one node per robot in the same episode",
    )
    r.add_argument(
        "--kill-node",
        type=_kill_spec,
        metavar="NODE@EPISODE:STEP",
        help="several nodes: kill that node's process before that step (its robot stops; the others go on)",
    )
    r.add_argument(
        "--node",
        choices=("c", "python"),
        default="c",
        help="c: the compiled node over SocketCAN vcan0 (the verdict); python: the Python reference node on "
        "python-can's virtual bus (no kernel, no build: the harness logic only)",
    )
    r.set_defaults(func=cmd_run)
    d = hil_sub.add_parser(
        "doctor", help="check every CAN sandbox provider on this machine (run this first when HIL fails)"
    )
    d.add_argument("--json", type=Path, help="also write the checks here")
    d.add_argument(
        "--sandbox", choices=MODES, default="auto", help="check only this provider's candidates (auto: all)"
    )
    d.set_defaults(func=cmd_doctor)


ERRORS: tuple[type[Exception], ...] = (HilError,)
