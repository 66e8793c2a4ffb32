"""One HIL run: the options checked against the export, the node built, the session run in a sandbox (or in
this process for the Python node), then the report and its verdict (:func:`run`).

The steps, each a function: :func:`check` (options alone, before any cost), :func:`check_export` (options
against the export's interface), :func:`_build_and_run` (node build, sandbox, session), then
:func:`embedrl.hil.report.hil_report` and :func:`embedrl.hil.verdict.verdict`.
"""

from __future__ import annotations

import json
import os
import shutil
import socket
import tempfile
from contextlib import AbstractContextManager, nullcontext
from dataclasses import asdict, replace
from pathlib import Path
from typing import TYPE_CHECKING, Any

from embedrl.common import read_json, sha256
from embedrl.export.contract import sources as can_sources
from embedrl.export.contract.errors import ContractError
from embedrl.export.contract.interface_file import load_interface
from embedrl.export.contract.layout import MAX_NODES
from embedrl.hil.errors import HilError
from embedrl.hil.faults import Scheduled, parse_schedule
from embedrl.hil.node_kinds import DEFAULT_NODE, NODE_KINDS, kinds_with
from embedrl.hil.options import DEFAULT_TIMEOUT_MS, MAX_TIMEOUT_MS, MIN_TIMEOUT_MS, RunOptions
from embedrl.hil.progress import episode_bar
from embedrl.train.interface import INTERFACE_FILE, NO_ENV, Interface

if TYPE_CHECKING:
    from embedrl.hil.sandbox import Guest
    from embedrl.hil.session import SessionConfig

REPO = Path(__file__).resolve().parents[1]
SESSION_TIMEOUT_S = 3600.0
"""A whole HIL session inside a guest (pure emulation runs Python about ten times slower)."""
ACTION_TIMEOUT_S = 2.0
"""How long the simulator waits for the node's answer to a step (on the host; stretched in slow guests)."""


NUMBER_WORDS = {2: "two", 3: "three", 4: "four"}
"""Counts of robots and nodes as messages spell them."""


def check(options: RunOptions) -> list[Scheduled]:
    """The options on their own (before anything is built); the fault schedule."""
    if options.episodes < 1:
        raise HilError(f"--episodes must be at least 1, got {options.episodes}")
    _check_node_kind(options)
    if options.timeout_ms is not None and not MIN_TIMEOUT_MS <= options.timeout_ms <= MAX_TIMEOUT_MS:
        raise HilError(
            f"--timeout-ms {options.timeout_ms}: the node's watchdog must be within {MIN_TIMEOUT_MS}.."
            f"{MAX_TIMEOUT_MS} ms; between two observations the node waits for the simulator's step and a "
            "CAN round trip (a few ms here, about ten times that in an emulated sandbox), so a shorter "
            "watchdog would trip in lock-step and fail the run blaming the node"
        )
    try:
        schedule = parse_schedule(list(options.inject))
    except ValueError as exc:
        raise HilError(str(exc)) from None
    if not 1 <= options.nodes <= MAX_NODES:
        raise HilError(f"--nodes must be within 1..{MAX_NODES}, got {options.nodes}")
    if options.nodes > 1 and (schedule or options.realtime):
        raise HilError("--nodes > 1 runs in lock-step without fault injection: drop --inject and --realtime")
    if options.kill_node is not None and options.kill_node[1] >= options.episodes:
        node, episode, step = options.kill_node
        raise HilError(f"--kill-node {node}@{episode}:{step}: the run has {options.episodes} episode(s)")
    for s in schedule:
        if s.episode >= options.episodes:
            raise HilError(
                f"--inject {s.injector.name}@{s.episode}:{s.step}: the run has {options.episodes} episode(s)"
            )
        if s.injector.needs_socketcan and not NODE_KINDS[options.node].own_socketcan:
            owners = kinds_with("own_socketcan")
            raise HilError(
                f"--inject {s.injector.name} acts on the node's own kernel CAN interface, which only "
                f"{' and '.join(NODE_KINDS[k].called for k in owners)} has: use --node {owners[0]}"
            )
    if options.target is not None:
        _check_target(options.target)
    if options.coverage is not None:
        _check_coverage(options.coverage)
    return schedule


def _check_coverage(folder: Path) -> None:
    """``--coverage``: its tools on PATH and a folder that is new or holds an earlier coverage run's files
    only (replaced once this run has its own: a report written again gets its coverage folder anew)."""
    from embedrl.hil.coverage import is_coverage_file
    from embedrl.hil.options import COVERAGE_TOOLS

    missing = [tool for tool in COVERAGE_TOOLS if shutil.which(tool) is None]
    if missing:
        raise HilError(
            f"--coverage needs {' and '.join(missing)}, not found on PATH (Debian: apt-get install clang-19 "
            "llvm-19)"
        )
    if folder.exists() and (not folder.is_dir() or not all(map(is_coverage_file, folder.iterdir()))):
        raise HilError(
            f"--coverage: {folder} holds other files than a coverage run's (*.profraw, policy_node); "
            "move them"
        )


def _check_node_kind(options: RunOptions) -> None:
    """The options the node kind cannot honour, refused; the programs it needs, looked for on PATH."""
    if options.node not in NODE_KINDS:
        raise HilError(f"--node {options.node}: not a node kind; use one of {', '.join(NODE_KINDS)}")
    kind = NODE_KINDS[options.node]
    for name, why in kind.refuses.items():
        if options.given(name):
            flag = "--" + name.replace("_", "-")
            raise HilError(f"{flag} does not apply to --node {options.node}: {why}; drop {flag}")
    missing = [tool for tool in kind.tools if shutil.which(tool) is None]
    if missing:
        raise HilError(
            f"--node {options.node} needs {' and '.join(missing)}, not found on PATH (Debian: "
            "gcc-arm-none-eabi, libnewlib-arm-none-eabi and qemu-system-arm; `make deps` installs them)"
        )


def _check_target(target: str) -> None:
    from embedrl.export.target import TARGETS

    if target not in TARGETS:
        raise HilError(f"--target {target}: not a Cortex-M target; use one of {', '.join(TARGETS)}")


def run(options: RunOptions, guest: Guest | None = None) -> dict[str, Any]:
    """The whole run: the report (the evaluation format plus the HIL keys) with ``verdict``, on ``guest``
    (None: the sandbox ``options.sandbox`` selects is booted and stopped)."""
    from embedrl.hil.report import hil_report
    from embedrl.hil.verdict import verdict

    schedule = check(options)
    if schedule and not options.allow_faults:
        print("note: injected faults change their episodes; without --allow-faults the run fails")
    options, interface = check_export(options, schedule)
    data = hil_report(options, interface, _in_work_folder(options, interface, guest))
    fired = {(r["kind"], r["episode"], r["step"]) for r in data["injections"] or []}
    data["injections_not_fired"] = [
        f"{s.injector.name}@{s.episode}:{s.step}"
        for s in schedule
        if (s.injector.name, s.episode, s.step) not in fired
    ]
    data["export_files"] = {
        name: sha256(options.export_dir / name)
        for name in chained_files(options)
        if (options.export_dir / name).is_file()
    }  # which bytes the verdict is about (embedrl.export.chain checks them)
    data["verdict"] = verdict(data, options.allow_faults)
    return data


CHAINED_FILES = ("policy.onnx", "interface.json", "c/policy.c")
"""The export's files every run's verdict is about; a node built from C adds its CAN code."""


def chained_files(options: RunOptions) -> tuple[str, ...]:
    """The export's files this run's verdict is about: :data:`CHAINED_FILES` and the CAN code the node was
    built from (``can/`` or ``can-fd/``)."""
    if not NODE_KINDS[options.node].builds_c:
        return CHAINED_FILES
    folder = can_sources.folder(options.fd)
    return (*CHAINED_FILES, *(f"{folder}/{name}" for name in can_sources.C_FILES))


HIL_FOLDER = "hil"
"""Where a HIL report written outside the export folder is kept in it, so the bundle holds its evidence."""


def in_bundle(export_dir: Path, report: Path) -> Path:
    """A HIL file's place in the bundle: itself if inside the export folder, else ``hil/<its name>``."""
    inside = report.resolve().is_relative_to(export_dir.resolve())
    return report if inside else export_dir / HIL_FOLDER / report.name


def bundle_path(export_dir: Path, file: Path) -> str:
    """A HIL file's path in the bundle, relative to the export folder (as the chain names it)."""
    return in_bundle(export_dir, file).resolve().relative_to(export_dir.resolve()).as_posix()


def keep_in_bundle(export_dir: Path, file: Path) -> Path:
    """Copy a file from outside the export folder to its place in ``hil/`` (atomically); its place."""
    place = in_bundle(export_dir, file)
    if place != file:
        place.parent.mkdir(exist_ok=True)
        partial = place.with_name(f".{place.name}.partial")
        shutil.copyfile(file, partial)
        os.replace(partial, place)
    return place


def add_to_chain(export_dir: Path, report: Path, data: dict[str, Any], log: Path | None = None) -> bool:
    """Append the written report (and the frame log it records) to the export's traceability chain, with
    the run as the step that made them; files written outside the export folder are copied into its
    ``hil/`` first, with the report's coverage folder (the bundle holds what its chain names). False for an
    export without a chain."""
    from embedrl.export import chain
    from embedrl.hil.coverage import recorded_files

    if not (export_dir / chain.MANIFEST).is_file():
        return False
    if log is not None and data.get("log"):
        keep_in_bundle(export_dir, log)
    place = keep_in_bundle(export_dir, report)
    for file, copy in recorded_files(report, place, data) if place != report else []:
        copy.parent.mkdir(exist_ok=True)
        shutil.copyfile(file, copy)  # the coverage folder travels with its report
    link_report(export_dir, place, data, made_by="hil run")
    return True


def link_report(export_dir: Path, report: Path, data: dict[str, Any], made_by: str | None = None) -> None:
    """Put the chain's links of a HIL report in the bundle and of the frame log it records (named by their
    paths there), with the step ``made_by`` (this process's command) that made them; the report's link
    stands for a link of the same bytes by digest only (an older manifest's report outside the folder)."""
    from embedrl.common import provenance
    from embedrl.export import chain
    from embedrl.export.pipeline import tool_version

    facts = {"passed": data["verdict"]["passed"], "node": data["node"], "target": data["target"],
             "episodes": data["episodes"], "node_binary_sha256": data.get("node_binary_sha256")}  # fmt: skip
    linked = {k.name for k in chain.read(export_dir)}
    files = data.get("export_files")
    can_code = [f"CAN code {path}" for path in files] if isinstance(files, dict) else []  # the built node's
    made_from = ["interface", "C source policy.c", "C source policy.h", *(n for n in can_code if n in linked)]
    found = chain.link(export_dir, "HIL report", report, made_from, **facts)
    new = replace(found, name=f"HIL report {found.path}")
    log = chain.recorded_log(data)
    if log is not None and (export_dir / log[0]).is_file():
        log_link = chain.link(export_dir, f"HIL log {log[0]}", export_dir / log[0], made_from)
        chain.append(export_dir, log_link)
    replaces = tuple(
        k.name
        for k in chain.read(export_dir)
        if k.name.startswith("HIL report") and not k.in_bundle and k.sha256 == new.sha256
    )
    step = None
    if made_by is not None:
        outputs = [new.name, *([f"HIL log {log[0]}"] if log else [])]
        step = chain.Step(made_by, f"embedrl {tool_version()}", list(provenance()["command"]), made_from,
                          outputs)  # fmt: skip
    chain.append(export_dir, new, step, replaces)


def onnx_of(export_dir: Path) -> Path:
    """The export's ONNX (``policy.onnx``; an older export's ONNX source)."""
    onnx = export_dir / "policy.onnx"
    if onnx.is_file():
        return onnx
    report = export_dir / "export_report.json"
    if report.is_file():
        source = Path(read_json(report)["source"]["path"])
        if source.suffix == ".onnx" and source.is_file():
            return source
    raise HilError(f"{export_dir}: no policy.onnx (is it an `embedrl export` folder?)")


def _export_interface(export_dir: Path) -> Interface:
    if not export_dir.is_dir():
        raise HilError(f"{export_dir}: no such folder (give an `embedrl export` folder)")
    if not (export_dir / "c" / "policy.c").is_file():
        raise HilError(
            f"{export_dir}: no c/policy.c (is it an `embedrl export` folder with the default --name?)"
        )
    onnx_of(export_dir)
    if not (export_dir / INTERFACE_FILE).is_file():
        raise HilError(
            f"{export_dir}: no {INTERFACE_FILE} (the policy's interface, from which the CAN database is "
            "generated): export it again with `embedrl export`"
        )
    try:
        return load_interface(export_dir / INTERFACE_FILE)  # untrusted: validated before use
    except ContractError as exc:
        raise HilError(str(exc)) from None


def _one_node_per_robot(options: RunOptions, interface: Interface) -> RunOptions:
    """The options of a scenario with several robots: one node per robot, in lock-step."""
    scenario, robots = interface.name, interface.robots
    one = NODE_KINDS[options.node].refuses.get("nodes")
    if one is not None:
        raise HilError(
            f"the {scenario} scenario needs {_count(robots)} nodes; {one}: use --node {DEFAULT_NODE}"
        )
    if robots > MAX_NODES:
        raise HilError(f"the {scenario} scenario has {robots} robots, one node each: at most {MAX_NODES}")
    if options.nodes not in (1, robots):
        raise HilError(f"the {scenario} scenario runs one node per robot: drop --nodes {options.nodes}")
    if options.inject or options.realtime:
        raise HilError(
            f"the {scenario} scenario runs its {_count(robots)} nodes in lock-step: drop --inject and "
            "--realtime (--kill-node takes a node down)"
        )
    return replace(options, nodes=robots)


def _count(n: int) -> str:
    """``n`` as a word for the small counts messages name (``two``), else as digits."""
    return NUMBER_WORDS.get(n, str(n))


def check_export(options: RunOptions, schedule: list[Scheduled]) -> tuple[RunOptions, Interface]:
    """The options against the export's interface; the options to run (the export folder resolved, one
    node per robot for a scenario with several) and the interface, read once for the whole run."""
    options = replace(options, export_dir=options.export_dir.resolve())
    interface = _export_interface(options.export_dir)
    if NODE_KINDS[options.node].builds_c and not options.trust_c:
        from embedrl.export.regenerate import mismatch

        problem = mismatch(options.export_dir, interface)
        if problem is not None:
            raise HilError(
                f"{problem}: the {options.node} node would build and run it, so only the generator's C runs "
                "(--trust-c runs C you trust)"
            )
    if options.nodes > 1 and interface.env_id == NO_ENV:
        raise HilError("a policy without an env runs in open loop on one node: drop --nodes")
    if interface.robots > 1:
        options = _one_node_per_robot(options, interface)
    for s in schedule:
        if s.step > interface.max_steps:
            raise HilError(
                f"--inject {s.injector.name}@{s.episode}:{s.step}: episodes of {interface.name!r} end by "
                f"step {interface.max_steps}, so the fault could never fire"
            )
    if options.kill_node is not None and options.nodes < 2:
        raise HilError("--kill-node takes one of several nodes down; with one node use --inject kill")
    if options.kill_node is not None and options.kill_node[0] >= options.nodes:
        raise HilError(f"--kill-node {options.kill_node[0]}: the run has nodes 0..{options.nodes - 1}")
    period_ms = interface.sample_time_s * 1000
    timeout_ms = options.timeout_ms or DEFAULT_TIMEOUT_MS
    if options.realtime and timeout_ms <= period_ms:
        raise HilError(
            f"--timeout-ms {timeout_ms} would trip the node's watchdog between real-time steps: "
            f"it must exceed the policy's sample time ({period_ms:.0f} ms)"
        )
    if NODE_KINDS[options.node].simulated_time and timeout_ms <= period_ms:
        raise HilError(
            f"--timeout-ms {timeout_ms} would trip the {options.node} node's watchdog at every step: its "
            f"clock is the simulation's, so it must exceed the policy's sample time ({period_ms:.0f} ms)"
        )
    return options, interface


def _in_work_folder(options: RunOptions, interface: Interface, guest: Guest | None) -> dict[str, Any]:
    """The session's results, run from a temporary work folder: removed after a successful run, kept and
    named after a failure."""
    work = Path(tempfile.mkdtemp(prefix="embedrl-hil-"))
    try:
        results = _build_and_run(options, interface, guest, work)
    except HilError as exc:
        raise HilError(f"{exc} [node build and guest console kept in {work}]") from None
    except BaseException:  # interrupted (SIGINT, SIGTERM): nothing to diagnose, nothing left behind
        if not options.keep_work:
            shutil.rmtree(work, ignore_errors=True)
        raise
    if options.keep_work:
        print(f"kept the node build and guest files in {work}")
    else:
        shutil.rmtree(work, ignore_errors=True)
    return results


def session_config(
    options: RunOptions, interface: Interface, slowdown: float = 1.0, **where: Any
) -> SessionConfig:
    """The session's settings; ``slowdown`` (the guest's, :attr:`Guest.slowdown`) stretches the wait for an
    answer and the default watchdog of a node on a real clock."""
    from embedrl.export.reference import OBSERVATIONS_FILE
    from embedrl.hil.session import SessionConfig

    export_dir = options.export_dir
    observations = export_dir / "test" / OBSERVATIONS_FILE
    env_id = interface.env_id
    if interface.robots > 1:
        nodes = f"of {_count(interface.robots)} robots, one node each, "
    elif options.nodes > 1:
        nodes = f"on each of {options.nodes} nodes "
    else:
        nodes = ""
    mode = (
        "in open loop (no env)"
        if env_id == NO_ENV
        else "in real time"
        if options.realtime
        else "in lock-step"
    )
    injecting = f", injecting {', '.join(options.inject)}" if options.inject else ""
    stretch = 1.0 if NODE_KINDS[options.node].simulated_time else slowdown  # simulated time is not slow
    print(f"running {options.episodes} episode(s) {nodes}{mode}{injecting}")
    return SessionConfig(
        onnx=str(onnx_of(export_dir)),
        export_dir=str(export_dir),
        interface=str(export_dir / INTERFACE_FILE),
        node=options.node,
        episodes=options.episodes,
        seed=options.seed,
        node_timeout_ms=round(options.timeout_ms or DEFAULT_TIMEOUT_MS * stretch),
        action_timeout_s=ACTION_TIMEOUT_S * slowdown,
        realtime=options.realtime,
        inject=options.inject,
        nodes=options.nodes,
        kill_node=options.kill_node,
        fd=options.fd,
        observations=str(observations) if observations.is_file() else None,
        **where,
    )


def _build_and_run(
    options: RunOptions, interface: Interface, guest: Guest | None, work: Path
) -> dict[str, Any]:
    kind = NODE_KINDS[options.node]
    if not kind.in_sandbox:
        return _python_session(options, interface, work)
    binary = work / "build" / "policy_node"
    if kind.host_binary:
        goal = "node" if options.coverage is None else "coverage-node"
        binary = make_node(options, interface, work, {"FD": "1"} if options.fd else {}, goal)
    return _guest_session(options, interface, guest, work, binary)


def make_node(
    options: RunOptions, interface: Interface, work: Path, extra: dict[str, str], goal: str = "node"
) -> Path:
    """``make -C runtime_c node``: the host node, or with ``TARGET`` the firmware image; its path. ``goal``
    ``coverage-node``: the host node instrumented for coverage. An export made before exports carried their
    CAN code gets it generated into ``work`` (``CAN_DIR``)."""
    from embedrl.export import build
    from embedrl.export.errors import BuildError

    fd = extra.get("FD") == "1"
    folder = can_sources.folder(fd)
    if not (options.export_dir / folder).is_dir():
        print(
            f"note: {options.export_dir} has no {folder}/ (made before exports carried their CAN code): "
            "generating it into the work folder; export the policy again to have it in the bundle"
        )
        try:
            can_sources.write(interface, work / folder, fd=fd)
        except ContractError as exc:
            raise HilError(str(exc)) from None
        extra = {**extra, "CAN_DIR": str(work / folder)}
    target = f" TARGET={extra['TARGET']}" if "TARGET" in extra else ""
    print(f"building the node: make -C runtime_c{target} {goal} POLICY_DIR={options.export_dir / 'c'}")
    try:
        build.make(goal, options.export_dir / "c", work / "build", extra=extra)
    except BuildError as exc:
        raise HilError(str(exc)) from None
    if "TARGET" in extra:
        return work / "build" / extra["TARGET"] / "node.elf"
    if goal == "coverage-node":
        return work / "build" / "coverage" / "policy_node"
    return work / "build" / "policy_node"


def _python_session(options: RunOptions, interface: Interface, work: Path) -> dict[str, Any]:
    """The reference node on python-can's virtual bus, in this process: no kernel, no build."""
    from embedrl.hil.session import run as run_session

    log = work / f"frames{options.log.suffix}" if options.log else None
    cfg = session_config(
        options, interface, bus="virtual", iface=f"embedrl-{os.getpid()}-{work.name}",
        log=str(log) if log else None, results=str(work / "results.json"), progress=str(work / "progress"),
    )  # fmt: skip
    with episode_bar(work / "progress", options.episodes):
        results = run_session(cfg, interface)
    _move_log(log, options.log)
    return {**results, "sandbox": "none", "sandbox_detail": "python-can virtual bus (Python reference node)"}


def _guest_session(
    options: RunOptions, interface: Interface, guest: Guest | None, work: Path, binary: Path
) -> dict[str, Any]:
    """The C node built in ``work`` (``binary``) and the session, both in ``guest`` (or the selected
    sandbox); the node's actions are compared with the reference here, after the session (the guest
    needs no ONNX runtime, and under emulation would take its time loading one)."""
    from embedrl.hil import compare, coverage, sandbox

    with nullcontext(guest) if guest else sandbox.opened(options.sandbox_mode, work / "sandbox") as where:
        if options.timeout_ms is None and where.slowdown > 1 and not NODE_KINDS[options.node].simulated_time:
            print(
                f"node watchdog {DEFAULT_TIMEOUT_MS * where.slowdown:.0f} ms: {where.provider} runs the "
                f"simulator ~{where.slowdown:.0f}x slower than the host (--timeout-ms sets another)"
            )
        scratch = where.scratch()  # the session's results and log: writable from inside the guest
        log = scratch / f"frames{options.log.suffix}" if options.log else None
        profiles = scratch / coverage.PROFILES  # the guest's node writes its profiles here
        cfg = session_config(
            options, interface, node_binary=str(binary), iface=where.iface,
            log=str(log) if log else None, results=str(scratch / "results.json"), slowdown=where.slowdown,
            progress=str(scratch / "progress"), compare=False,
            coverage_profile=str(profiles / coverage.PROFILE_PATTERN) if options.coverage else None,
        )  # fmt: skip
        emulator: AbstractContextManager[None] = nullcontext()
        image = NODE_KINDS[options.node].firmware_image
        if image:  # its watchdog is fixed in the image: built for this sandbox
            cfg = _with_firmware(options, interface, cfg, work)
            if where.link is not None:  # QEMU on this machine, its UART0 on the guest's serial line
                cfg = replace(cfg, firmware_link=where.link.device, firmware_control=str(scratch / "qemu"))
                emulator = _qemu_on_host(cfg, where.link.host)
        config_file = scratch / "session.json"
        config_file.write_text(json.dumps(asdict(cfg)))
        with emulator, episode_bar(scratch / "progress", options.episodes):
            argv = [where.python, "-m", "embedrl.hil.session", str(config_file)]
            job = where.run(argv, REPO, timeout_s=SESSION_TIMEOUT_S)
        if job.status != 0 or not Path(cfg.results).is_file():
            why = where.diagnose(f"the HIL session failed (status {job.status}): {job.last_lines()}")
            raise HilError(str(why))
        results: dict[str, Any] = json.loads(Path(cfg.results).read_text())
        compare.fill(results, interface, lambda: compare.reference(cfg.export_dir, cfg.onnx))
        binary = Path(cfg.node_binary or "")
        if image:
            results["firmware"]["stack_bound"] = _firmware_stack_bound(options, binary)
        results["node_binary_sha256"] = sha256(binary)  # which bytes these verdicts are about
        if options.coverage is not None:
            results["coverage"] = coverage.keep(profiles, binary, options.coverage)
        _move_log(log, options.log)
        results["sandbox"] = where.provider
        results["sandbox_detail"] = where.description
        shutil.rmtree(scratch, ignore_errors=True)
    return results


def _with_firmware(
    options: RunOptions, interface: Interface, cfg: SessionConfig, work: Path
) -> SessionConfig:
    """The firmware image built with the session's watchdog and recovery count, and its board."""
    from embedrl.export.target import TARGETS

    extra = {"TARGET": options.firmware_target, "NODE_TIMEOUT_MS": str(cfg.node_timeout_ms),
             "NODE_RECOVER": str(cfg.node_recover)}  # fmt: skip
    elf = make_node(options, interface, work, extra)
    target = TARGETS[options.firmware_target]
    return replace(
        cfg,
        node_binary=str(elf),
        qemu_machine=target.qemu_machine,
        tick_instructions=target.tick_instructions,
    )


def _qemu_on_host(cfg: SessionConfig, link: socket.socket) -> AbstractContextManager[None]:
    """The firmware's QEMU served on this machine for the session (:func:`.firmware.serve_qemu`)."""
    from embedrl.hil.firmware import serve_qemu

    assert cfg.node_binary is not None and cfg.qemu_machine is not None and cfg.firmware_control is not None
    return serve_qemu(cfg.node_binary, cfg.qemu_machine, link, Path(cfg.firmware_control))


def _firmware_stack_bound(options: RunOptions, elf: Path) -> dict[str, Any]:
    """The static bound of the image that ran (:func:`embedrl.export.stack.node_bound`)."""
    from embedrl.export import stack
    from embedrl.export.target import TARGETS

    try:
        return stack.node_bound(elf, fpu=TARGETS[options.firmware_target].has_fpu)
    except stack.StackError as exc:
        raise HilError(f"the firmware node's stack: {exc}") from None


def _move_log(written: Path | None, wanted: Path | None) -> None:
    if written is not None and wanted is not None:
        wanted.parent.mkdir(parents=True, exist_ok=True)
        shutil.move(written, wanted)
