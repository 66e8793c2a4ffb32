"""``embedrl hil run`` and ``embedrl hil doctor``: options in, the library's run (:mod:`embedrl.hil.run`)
and doctor (:mod:`embedrl.hil.doctor`) called, their summary printed."""

from __future__ import annotations

import argparse
from pathlib import Path
from typing import Any

from embedrl.export.contract.layout import WATCHDOG_MS
from embedrl.export.target import TARGETS
from embedrl.hil.errors import HilError
from embedrl.hil.faults import INJECT_STEP, INJECTORS
from embedrl.hil.node_kinds import DEFAULT_NODE, NODE_KINDS, cli_help
from embedrl.hil.options import DEFAULT_SANDBOX, DEFAULT_TARGET, MAX_TIMEOUT_MS, MIN_TIMEOUT_MS
from embedrl.hil.sandbox import AUTO, MODES, mode_help
from embedrl.train import arguments
from embedrl.train.arguments import add_export_dir_argument


def cmd_run(args: argparse.Namespace) -> int:
    from embedrl.common import sha256, table, write_json
    from embedrl.export import chain
    from embedrl.hil import coverage
    from embedrl.hil.options import RunOptions
    from embedrl.hil.run import add_to_chain, bundle_path, in_bundle, run
    from embedrl.hil.verdict import summary_rows

    if args.coverage and not args.json:
        raise HilError("--coverage keeps the node's profiles beside the report: give --json REPORT.json")
    if args.json and (args.export_dir / chain.MANIFEST).is_file():
        chain.check_appendable(args.export_dir)  # before the run: its report's link is written at the end
    folder = coverage.folder_of(args.json) if args.coverage else None
    data = run(RunOptions.of({**vars(args), "coverage": folder}))
    print(table(summary_rows(data)))
    pictures = sorted([*args.plot.glob("hil_*.png"), *args.plot.glob("hil_*.gif")]) if args.plot else []
    written = [str(p) for p in (args.json, args.log, *pictures) if p]
    if folder is not None:
        record = data["coverage"]
        left = len(record["unreadable"])
        left_out = f"; {left} empty or cut short (a process killed), left out" if left else ""
        written.append(f"{folder} ({len(record['profiles'])} profile(s) of the node{left_out})")
    chained = args.json and (args.export_dir / chain.MANIFEST).is_file()
    if chained and args.log and args.log.is_file():  # the bundle keeps the frames beside the report
        data["log"] = {"file": bundle_path(args.export_dir, args.log), "sha256": sha256(args.log)}
    if args.json:
        write_json(data, args.json)
        if add_to_chain(args.export_dir, args.json, data, args.log):
            files = [args.json, *([args.log] if "log" in data else [])]
            copies = [str(in_bundle(args.export_dir, p)) for p in files if in_bundle(args.export_dir, p) != p]
            also = f"{', '.join(copies)} (copies in the bundle) and " if copies else ""
            written.append(f"{also}{args.export_dir / 'chain.json'} (the report's link)")
    if written:
        print(f"wrote {', '.join(written)}")
    return 0 if data["verdict"]["passed"] else 1


def cmd_report(args: argparse.Namespace) -> int:
    from embedrl.hil import signoff

    data = signoff.write(args.export_dir, args.hil, args.also, args.out, args.sign, args.key)
    unexplained = len(data["coding_standard"]["unexplained"])
    intact = all(link["ok"] for link in data["chain"])
    print(
        f"wrote {args.out}: {len(data['targets'])} target(s), {len(data['hil_reports'])} HIL report(s), "
        f"MISRA {data['coding_standard']['findings']} findings ({unexplained} unexplained), "
        f"chain {'intact' if intact else 'BROKEN'}"
    )
    verdict = data["verdict"]
    for check in verdict["checks"]:
        print(f"  {'PASS' if check['passed'] else 'FAIL'}  {check['check']}: {check['detail']}")
    for warning in verdict.get("warnings", []):
        print(f"  WARN  {warning}")
    print(f"verdict: {'PASS' if verdict['passed'] else 'FAIL'}")
    return 0 if verdict["passed"] else 1


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

    report = doctor(say=print, mode=args.sandbox, every=args.all)
    print_table(report)
    if args.json:
        write_json(report, args.json)
        print(f"wrote {args.json}")
    return 0 if report["first_working"] else 1


def register(sub: Any) -> None:
    p = sub.add_parser("hil", help="hardware-in-the-loop over virtual SocketCAN")
    hil_sub = p.add_subparsers(dest="hil_command", required=True, metavar="COMMAND")
    r = hil_sub.add_parser("run", help="run episodes with the exported C policy as a CAN node")
    add_export_dir_argument(r, "an `embedrl export` folder")
    r.add_argument("--episodes", type=int, default=10, help="episodes in the loop")
    r.add_argument("--seed", type=arguments.seed, default=0, help="episode i is reset with seed + i")
    r.add_argument(
        "--realtime", action="store_true", help="pace at the env's sample time (a report, not a verdict)"
    )
    r.add_argument("--log", type=Path, help="write every frame here (candump format, .log; .blf also works)")
    r.add_argument("--json", type=Path, help="write the report here")
    r.add_argument("--plot", type=Path, help="write trajectories and the latency histogram into this folder")
    r.add_argument(
        "--sandbox",
        choices=MODES,
        help=f"where vcan0 comes from, for the nodes that run in a sandbox ({mode_help()}) "
        f"(default: {DEFAULT_SANDBOX})",
    )
    r.add_argument(
        "--timeout-ms",
        type=int,
        help=f"the node's watchdog in ms, {MIN_TIMEOUT_MS}..{MAX_TIMEOUT_MS}; with --realtime it must exceed "
        f"the policy's sample time (default: {WATCHDOG_MS}, times the sandbox's slowdown: 10 under "
        "QEMU emulation)",
    )
    r.add_argument(
        "--inject",
        action="append",
        default=[],
        metavar="FAULT[@EPISODE:STEP]",
        help=f"inject a fault, at step {INJECT_STEP} of episode 0 unless @EPISODE:STEP says when "
        "(repeatable): " + ", ".join(INJECTORS),
    )
    r.add_argument(
        "--allow-faults",
        action="store_true",
        help="pass even if episodes end in a fault (fault-injection runs); without it a fault fails the run",
    )
    r.add_argument("--keep-work", action="store_true", help="keep the temporary node build and guest files")
    r.add_argument(
        "--coverage",
        action="store_true",
        help="run the C node built with clang's coverage flags (clang-19, llvm-19) and keep each node "
        "process's profile and the binary beside the report (--json NAME.json: NAME.coverage/), for embedrl "
        "report",
    )
    _add_node_arguments(r)
    r.set_defaults(func=cmd_run)
    _register_bench(hil_sub)
    _register_doctor(hil_sub)
    _register_report(sub)
    _register_scope(sub)


def _add_node_arguments(r: Any) -> None:
    """``hil run``'s options about the node: its kind, core, frames, count and what it may build."""
    r.add_argument(
        "--trust-c",
        action="store_true",
        help="build and run the export's C even if it is not what embedrl generates from its ONNX "
        "(edited by hand); without it such C is refused before anything is built",
    )
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
        "an export of a scenario with several robots always runs one node per robot in the same episode",
    )
    r.add_argument(
        "--kill-node",
        type=_kill_spec,
        metavar="NODE@EPISODE:STEP",
        help="several nodes: kill that node's process before that step (its robot stops; the others go on)",
    )
    r.add_argument(
        "--node",
        choices=tuple(NODE_KINDS),
        default=DEFAULT_NODE,
        help=cli_help(),
    )
    r.add_argument(
        "--target",
        choices=tuple(TARGETS),
        help=f"the firmware node's core (runtime_c/cortex_m/targets.mk) (default: {DEFAULT_TARGET})",
    )


def cmd_scope(args: argparse.Namespace) -> int:
    from embedrl.hil import scope
    from embedrl.train.arguments import policy_from
    from embedrl.train.scenarios import SCENARIOS

    if args.out.suffix.lower() != ".png":
        raise HilError(f"cannot write {args.out}: the scope view is a .png file")
    policy = policy_from(args)
    robots = SCENARIOS[args.scenario].robots
    extra = {"partner": policy} if robots > 1 else {}  # one policy drives every robot
    episode = scope.record(policy, args.scenario, args.seed, extra)
    scope.plot(episode, args.out, args.controller or args.model.name)
    print(f"wrote {args.out}: {len(episode['actions'])} steps, {episode['outcome']}")
    return 0


def _register_scope(sub: Any) -> None:
    from embedrl.train.arguments import add_policy_arguments

    p = sub.add_parser(
        "scope", help="one episode against time, as a scope shows a controller: observations, actions and "
        "what the CAN signals make of them (PNG)",
    )  # fmt: skip
    add_policy_arguments(p)
    p.add_argument("--seed", type=arguments.seed, default=0, help="the episode's reset seed")
    p.add_argument("--out", type=Path, required=True, help="the picture (.png)")
    p.set_defaults(func=cmd_scope)


def _register_report(sub: Any) -> None:
    p = sub.add_parser(
        "report",
        help="the deployment report: one self-contained HTML page (interface, verification, closed loop, "
        "target resources, MISRA, traceability)",
    )
    add_export_dir_argument(p, "an `embedrl export` folder")
    p.add_argument(
        "--hil", type=Path, action="append", default=[], metavar="REPORT.json",
        help="a report of `embedrl hil run --json` on this export (repeatable: host node, firmware node); "
        "one outside the export folder is copied into its hil/ and joins the chain there",
    )  # fmt: skip
    p.add_argument(
        "--also", type=Path, action="append", default=[], metavar="EXPORT_DIR",
        help="another export of the same policy in another precision, for the error histograms (repeatable)",
    )  # fmt: skip
    p.add_argument("--out", type=Path, required=True, help="the HTML file to write")
    p.add_argument(
        "--sign", type=Path, metavar="PRIVATE.pem",
        help="sign the export's chain (with the HIL reports gathered into it) with this Ed25519 private key "
        "(PEM); only an intact chain is signed",
    )  # fmt: skip
    p.add_argument(
        "--key", type=Path, metavar="PUBLIC.pem",
        help="check the chain's signature with this Ed25519 public key (PEM) (default: --sign's)",
    )  # fmt: skip
    p.set_defaults(func=cmd_report)


def cmd_bench(args: argparse.Namespace) -> int:
    from embedrl.common import print_measurement
    from embedrl.hil.options import RunOptions
    from embedrl.hil.round_trip import run_bench

    if args.exchanges < 1 or args.episodes < 1:
        raise HilError("--exchanges and --episodes must be at least 1")
    options = RunOptions(export_dir=args.export_dir, episodes=args.episodes, sandbox=args.sandbox)
    result = run_bench(options, args.exchanges)
    floor, hil = result["floor"], result["lockstep"]
    print_measurement(
        {
            "sandbox": result["sandbox"],
            "bus_floor_exchanges_per_second": round(floor["per_second"]),
            "bus_floor_us_per_exchange": round(1e6 / floor["per_second"], 1),
            "hil_lockstep_steps_per_second": round(hil["per_second"]),
            "hil_lockstep_us_per_step": round(1e6 / hil["per_second"], 1),
            "hil_steps": hil["steps"],
            "ratio_to_floor": round(result["ratio"], 3),
        },
        args.json,
    )
    return 0


def _register_bench(hil_sub: Any) -> None:
    b = hil_sub.add_parser(
        "bench", help="the HIL lock-step rate against the bus's floor (a trivial C responder), same sandbox"
    )
    add_export_dir_argument(b, "an `embedrl export` folder")
    b.add_argument("--episodes", type=int, default=20, help="HIL episodes of the lock-step measurement")
    b.add_argument("--exchanges", type=int, default=2000, help="exchanges of the floor measurement")
    b.add_argument("--sandbox", choices=MODES, default=AUTO, help="where vcan0 comes from (as hil run)")
    b.add_argument("--json", type=Path, help="write the measurement here")
    b.set_defaults(func=cmd_bench)


def _register_doctor(hil_sub: Any) -> None:
    d = hil_sub.add_parser(
        "doctor", help="check every CAN sandbox provider on this machine (run this first when HIL fails)"
    )
    d.add_argument("--json", type=Path, help="also write the checks here")
    d.add_argument(
        "--sandbox", choices=MODES, default=AUTO, help=f"check only this provider's candidates ({AUTO}: all)"
    )
    d.add_argument(
        "--all", action="store_true",
        help="check every provider, not only up to the first that works (a QEMU guest's boot takes minutes)",
    )  # fmt: skip
    d.set_defaults(func=cmd_doctor)


ERRORS: tuple[type[Exception], ...] = (HilError,)
