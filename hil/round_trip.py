"""``embedrl hil bench``: the HIL lock-step rate against the bus's floor, in the same sandbox and run.

The floor: the simulator's side of an exchange (one step's observation frames encoded and sent through the
same :class:`~embedrl.hil.link.Link` and socket, the answer received and decoded) against a trivial C
responder (``runtime_c/bench/can_responder.c``: receives a step's observation frames as the node does and
answers the last with one action frame at once: no E2E check, no inference). The lock-step rate: the HIL
session with the C node (:func:`embedrl.hil.session.run`), steps per second of its episodes' wall-clock
time (the environment and every check included; the session's comparison with the reference policy comes
after its episodes and is skipped here). Their ratio says how much of the bus's speed a HIL step uses.

Inside the guest this module runs as ``python -m embedrl.hil.round_trip CONFIG.json``.
"""

from __future__ import annotations

import json
import subprocess
import sys
import time
from dataclasses import asdict
from pathlib import Path
from statistics import median
from typing import Any

import numpy as np

WARMUP_EXCHANGES = 50
"""Exchanges before the floor's clock starts (sockets, caches, the responder's first wake-up)."""
EXCHANGE_TIMEOUT_S = 2.0
ROUNDS = 3
"""Interleaved rounds of the two measurements; each reported figure is the median over them."""


def floor(session: dict[str, Any], responder: str, exchanges: int) -> dict[str, Any]:
    """Exchanges per second between this process and the trivial responder, on ``session``'s interface."""
    from embedrl.export.contract.interface_file import load_interface
    from embedrl.hil.codec import Codec
    from embedrl.hil.link import Link, Stats
    from embedrl.hil.session import SessionConfig, open_bus

    cfg = SessionConfig(**session)
    interface = load_interface(Path(cfg.interface))
    codec = Codec(interface)
    ids = [frame_id for _, frame_id, _ in codec.plan.observation]
    if ids != list(range(ids[0], ids[0] + len(ids))):
        raise ValueError(f"the responder takes consecutive observation IDs, not {ids}")
    reply = codec.plan.action[0][1]
    length = codec.db.get_message_by_frame_id(reply).length
    argv = [responder, cfg.iface, f"{ids[0]:x}", str(len(ids)), f"{reply:x}", str(length)]
    process = subprocess.Popen(argv, stdout=subprocess.PIPE, text=True)
    try:
        if process.stdout is None or process.stdout.readline().strip() != "ready":
            raise RuntimeError(f"the responder did not start: {' '.join(argv)}")
        bus = open_bus(cfg, codec)
        link = Link(bus, codec, Stats(), cfg.iface, None)
        obs = np.zeros(len(interface.observation), dtype=np.float32)
        try:
            for _ in range(WARMUP_EXCHANGES):
                _exchange(link, obs, 0)
            start = time.perf_counter()
            for step in range(exchanges):
                _exchange(link, obs, step)
            seconds = time.perf_counter() - start
        finally:
            bus.shutdown()
    finally:
        process.kill()
        process.wait()
    return {"exchanges": exchanges, "seconds": seconds, "per_second": exchanges / seconds,
            "frames_out_per_exchange": len(codec.plan.observation), "frames_back": 1}  # fmt: skip


def _exchange(link: Any, obs: np.ndarray, step: int) -> None:
    frames, _ = link.codec.encode_observation(obs, step)
    link.send(frames)
    if link.receive(EXCHANGE_TIMEOUT_S) is False:
        raise RuntimeError("the responder did not answer within 2 s")


def lockstep(session: dict[str, Any]) -> dict[str, Any]:
    """The HIL session's steps per second over its episodes (lock-step, the C node)."""
    from embedrl.hil.session import SessionConfig, run

    results = run(SessionConfig(**session))
    steps = sum(e["steps"] for e in results["episodes"])
    return {"steps": steps, "seconds": results["loop_seconds"], "per_second": steps / results["loop_seconds"],
            "faults": sum(e["fault"] is not None for e in results["episodes"])}  # fmt: skip


def measure(config: dict[str, Any]) -> dict[str, Any]:
    """Both, in :data:`ROUNDS` interleaved rounds in this process (the guest): the medians and their ratio
    (the guest's speed drifts: interleaving puts the same drift on both sides)."""
    session, rounds = config["session"], config.get("rounds", ROUNDS)
    per_round = max(1, session["episodes"] // rounds)
    floors, hils = [], []
    for r in range(rounds):
        floors.append(floor(session, config["responder"], max(1, config["exchanges"] // rounds)))
        hils.append(lockstep({**session, "episodes": per_round, "seed": session["seed"] + r * per_round}))
    bus_floor = {
        **floors[-1], "per_second": median(f["per_second"] for f in floors),
        "exchanges": sum(f["exchanges"] for f in floors), "rounds": [f["per_second"] for f in floors],
    }  # fmt: skip
    hil = {
        "per_second": median(h["per_second"] for h in hils), "steps": sum(h["steps"] for h in hils),
        "faults": sum(h["faults"] for h in hils), "rounds": [h["per_second"] for h in hils],
    }  # fmt: skip
    return {"floor": bus_floor, "lockstep": hil, "ratio": hil["per_second"] / bus_floor["per_second"]}


def main(argv: list[str]) -> int:
    config = json.loads(Path(argv[0]).read_text())
    result = measure(config)
    Path(config["out"]).write_text(json.dumps(result, indent=2) + "\n")
    return 0


def run_bench(options: Any, exchanges: int, guest: Any = None) -> dict[str, Any]:
    """On the host: build the C node and the responder, measure both in ``guest`` (None: the sandbox
    ``options.sandbox`` selects, booted and stopped); the measurement with the sandbox's name."""
    import shutil
    import tempfile
    from contextlib import nullcontext

    from embedrl.export import build
    from embedrl.export.errors import BuildError
    from embedrl.hil import sandbox
    from embedrl.hil.errors import HilError
    from embedrl.hil.run import REPO, SESSION_TIMEOUT_S, check, check_export, make_node, session_config

    options, interface = check_export(options, check(options))
    if interface.robots > 1:
        raise HilError(
            f"{options.export_dir}: hil bench measures one node on one robot; this export runs one node per "
            f"robot of the {interface.name} scenario (export a one-robot policy)"
        )
    work = Path(tempfile.mkdtemp(prefix="embedrl-hil-bench-"))
    try:
        make_node(options, interface, work, {})
        try:
            build.make("responder", options.export_dir / "c", work / "build")
        except BuildError as exc:
            raise HilError(str(exc)) from None
        with nullcontext(guest) if guest else sandbox.opened(options.sandbox_mode, work / "sandbox") as where:
            scratch = where.scratch()
            cfg = session_config(options, interface, node_binary=str(work / "build" / "policy_node"),
                                 iface=where.iface, results=str(scratch / "results.json"),
                                 slowdown=where.slowdown, compare=False)  # fmt: skip
            config = {"session": asdict(cfg), "responder": str(work / "build" / "can_responder"),
                      "exchanges": exchanges, "out": str(scratch / "bench.json")}  # fmt: skip
            (scratch / "config.json").write_text(json.dumps(config))
            argv = [where.python, "-m", "embedrl.hil.round_trip", str(scratch / "config.json")]
            job = where.run(argv, REPO, timeout_s=SESSION_TIMEOUT_S)
            if job.status != 0 or not (scratch / "bench.json").is_file():
                raise HilError(str(where.diagnose(f"the HIL benchmark failed (status {job.status}): "
                                                  f"{job.last_lines()}")))  # fmt: skip
            result: dict[str, Any] = json.loads((scratch / "bench.json").read_text())
            result["sandbox"] = where.description
    finally:
        shutil.rmtree(work, ignore_errors=True)
    return result


if __name__ == "__main__":
    sys.exit(main(sys.argv[1:]))
