"""What the deployment report states, gathered from an export folder and the HIL reports made on it:
the interface and its CAN frames, the numerical verification recomputed per sample, the closed loop on
each platform, the target resources, the coding standard and the traceability chain.

Every file read here is the user's: JSON is parsed without executing anything, the C is rebuilt from
the export's sources rather than a binary in the folder loaded, and a HIL report made on other bytes
than this export's is refused.
"""

from __future__ import annotations

import math
import subprocess
from collections.abc import Sequence
from pathlib import Path
from typing import Any

import numpy as np

from embedrl.common import owned_temporary_folder, read_json, sha256
from embedrl.export.contract.dbc import frame_rows
from embedrl.export.contract.interface_file import load_interface
from embedrl.export.contract.layout import WATCHDOG_MS
from embedrl.export.report_schema import check_export_report
from embedrl.hil.errors import HilError
from embedrl.train.interface import INTERFACE_FILE

TOP_SYMBOLS = 12
"""Largest symbols listed per image."""
RAM_ORIGIN = 0x20000000
"""Where the targets' RAM starts (runtime_c/Makefile's memory.ld): symbols below it are in flash."""
ELF_MAGIC = b"\x7fELF"
IDENTICAL = "identical to the generator's"
"""A verification row's ``generated_c`` when the export's C is what embedrl generates from its ONNX."""
SECTIONS = (".isr_vector", ".text", ".ARM.exidx", ".data", ".bss", ".heap", ".stack")


def load_export(export_dir: Path) -> dict[str, Any]:
    """The export's report and interface; a folder that is not an export is refused in one line."""
    report = export_dir / "export_report.json"
    if not export_dir.is_dir():
        raise HilError(f"{export_dir}: no such folder")
    if not report.is_file() or not (export_dir / INTERFACE_FILE).is_file():
        raise HilError(
            f"{export_dir}: not an `embedrl export` folder (no export_report.json or interface.json)"
        )
    try:
        data = read_json(report)
        check_export_report(data)
    except (ValueError, KeyError, TypeError) as exc:
        raise HilError(f"{report}: not an export report ({exc})") from None
    name = data.get("name")
    if not isinstance(name, str) or not name.isidentifier():
        raise HilError(f"{report}: the policy's name {name!r} is not a C identifier")
    for generated in (f"{name}.c", f"{name}.h"):
        if not (export_dir / "c" / generated).is_file():
            raise HilError(
                f"{report} names the policy {name!r}, but there is no c/{generated}: the report is not this "
                "export's (export it again)"
            )
    return dict(data)


def check_same_policy(export_dir: Path, other: Path) -> None:
    """Refuse ``other`` (``--also``) unless it exports the same ONNX as ``export_dir`` (the same policy,
    maybe in another precision): its errors would otherwise share one table with another policy's."""
    digests = []
    for folder in (export_dir, other):
        onnx = folder / "policy.onnx"
        if not onnx.is_file():
            raise HilError(f"{folder}: no policy.onnx (is it an `embedrl export` folder?)")
        digests.append(sha256(onnx))
    if digests[0] != digests[1]:
        raise HilError(
            f"--also {other} exports another policy: its policy.onnx (sha256 {digests[1][:12]}...) is not "
            f"{export_dir}'s (sha256 {digests[0][:12]}...); --also takes the same policy in another precision"
        )


def load_hil(path: Path, export_dir: Path) -> dict[str, Any]:
    """A HIL report made on exactly this export's files, each key the page reads of the type it needs."""
    try:
        data = read_json(path)
        _check_hil(data)
    except (OSError, ValueError, KeyError, TypeError) as exc:
        raise HilError(f"{path}: not a HIL report of `embedrl hil run --json` ({exc})") from None
    for name, recorded in data["export_files"].items():
        if not (export_dir / name).is_file() or sha256(export_dir / name) != recorded:
            raise HilError(f"{path} was made on another export: its {name} differs from {export_dir}'s")
    missing = missing_files(data["node"], export_dir, data["export_files"])
    if missing:
        raise HilError(
            f"{path} does not name the export files it ran with: {', '.join(missing)} missing from its "
            "export_files (a run records every file its verdict is about)"
        )
    return dict(data)


def missing_files(node: str, export_dir: Path, recorded: dict[str, str]) -> list[str]:
    """The export's files a HIL run of node kind ``node`` must record and ``recorded`` lacks: those every
    run's verdict is about (where the export has them), and for a node built from C the CAN code of one of
    the folders (``can/`` or ``can-fd/``) complete."""
    from embedrl.export.contract import sources as can_sources
    from embedrl.hil.node_kinds import NODE_KINDS
    from embedrl.hil.run import CHAINED_FILES

    missing = [name for name in CHAINED_FILES if (export_dir / name).is_file() and name not in recorded]
    if NODE_KINDS[node].builds_c and (export_dir / INTERFACE_FILE).is_file():
        sets = [[f"{can_sources.folder(fd)}/{name}" for name in can_sources.C_FILES] for fd in (False, True)]
        if not any(all(name in recorded for name in names) for names in sets):
            missing.append("the CAN code it was built from (can/ or can-fd/)")
    return missing


def _on_firmware(hil: dict[str, Any]) -> bool:
    """Whether a HIL report's node was a firmware image on an emulated target."""
    from embedrl.hil.node_kinds import NODE_KINDS

    kind = NODE_KINDS.get(hil.get("node", ""))
    return kind is not None and kind.firmware_image


def _check_hil(data: Any) -> None:
    """ValueError naming the first key the page reads that is missing or of another type."""
    from embedrl.hil.node_kinds import NODE_KINDS

    def expect(where: dict[str, Any], key: str, kinds: tuple[type, ...], what: str) -> Any:
        if key not in where:
            raise ValueError(f"no {key!r}")
        if not isinstance(where[key], kinds) or (isinstance(where[key], bool) and bool not in kinds):
            raise ValueError(f"{key!r} is {where[key]!r}, not {what}")
        return where[key]

    if not isinstance(data, dict):
        raise ValueError(f"a {type(data).__name__}, not an object")
    files = expect(data, "export_files", (dict,), "an object of file names and hashes")
    if not all(isinstance(k, str) and isinstance(v, str) for k, v in files.items()):
        raise ValueError("'export_files' is not an object of file names and hashes")
    expect(expect(data, "verdict", (dict,), "an object"), "passed", (bool,), "true or false")
    node = expect(data, "node", (str,), "a node kind")
    if node not in NODE_KINDS:
        raise ValueError(f"'node' is {node!r}, not one of {', '.join(NODE_KINDS)}")
    expect(data, "target", (str, type(None)), "a target's name or null")
    _check_counts(data, expect)
    expect(data, "simulation", (dict, type(None)), "an object or null")
    image = NODE_KINDS[node].firmware_image
    firmware = expect(data, "firmware", (dict,) if image else (dict, type(None)), "an object")
    if image:
        expect(firmware, "stack_peak_bytes", (int, type(None)), "a number of bytes or null")
        step = expect(data, "time_on_target", (dict, type(None)), "an object or null")
        if step is not None:
            expect(step, "estimated_step_us", (int, float), "a number")
            expect(step, "margin_s", (int, float), "a number")


OUTCOME_COUNTS = {"successes": "success", "collisions": "collision", "timeouts": "timeout"}
"""A HIL report's counts and the per-episode outcome each one counts."""


def _check_counts(data: dict[str, Any], expect: Any) -> None:
    """The report's counts against its own rows: episodes, successes, collisions and timeouts recounted from
    ``per_episode``, the success rate recomputed (a report is a file anyone can edit)."""
    rows = expect(data, "per_episode", (list,), "a list of episodes")
    if not all(isinstance(r, dict) and isinstance(r.get("outcome"), str) for r in rows):
        raise ValueError("'per_episode' is not a list of episodes with their outcomes")
    episodes = expect(data, "episodes", (int,), "a number of episodes")
    if episodes != len(rows):
        raise ValueError(f"'episodes' is {episodes} but 'per_episode' has {len(rows)} rows")
    for key, outcome in OUTCOME_COUNTS.items():
        counted = sum(r["outcome"] == outcome for r in rows)
        if expect(data, key, (int,), "a count") != counted:
            raise ValueError(f"'{key}' is {data[key]} but {counted} of its episodes ended in {outcome}")
    rate = expect(data, "success_rate", (int, float), "a number")
    if rows and abs(rate - data["successes"] / len(rows)) > 1e-9:
        raise ValueError(f"'success_rate' is {rate}, not its successes over its episodes")


def interface_facts(export: dict[str, Any], export_dir: Path) -> dict[str, Any]:
    interface = load_interface(export_dir / INTERFACE_FILE)
    return {
        "name": interface.name,
        "sample_time_s": interface.sample_time_s,
        "safe_action": list(interface.safe_action),
        "observation": export["interface"]["observation"],
        "action": export["interface"]["action"],
        "frames": frame_rows(interface),
        "watchdog_ms": WATCHDOG_MS,
    }


def recompute(export_dir: Path, export: dict[str, Any]) -> dict[str, Any]:
    """The numerical verification of an export done again, never copied from its report: the C generated
    again from its ONNX must equal ``c/`` byte for byte (else none of it is built or run on this host, and
    the row fails); then it is built and run on the export's observations against the float ONNX
    (``max |C - ONNX|`` per sample; a quantised policy's is its quantisation error) and, quantised, against
    its integer model bit for bit. ``passed``: the C is the generator's, and float32 within the export's
    tolerance (``tolerance x max(1, |ONNX|)`` per output) or quantised bit-exact with its model."""
    from embedrl.export import build, quantize, verify
    from embedrl.export.reference import OnnxPolicy, precision_of
    from embedrl.export.regenerate import regenerate

    precision = precision_of(export_dir)
    source = export["verification"].get("onnx_vs_sb3_max_abs_error")
    row: dict[str, Any] = {
        "precision": precision, "samples": 0, "max_error": None, "p99_error": None, "errors": np.zeros(0),
        "bit_exact_with_model": None, "onnx_vs_source": source, "generated_c": None, "passed": False,
        "max_ulp": None,
    }  # fmt: skip
    again = regenerate(export_dir)
    problem = again if isinstance(again, str) else again.problem
    if problem is not None or isinstance(again, str):
        row["generated_c"] = problem
        return row
    observations = again.observations
    expected = OnnxPolicy(export_dir / "policy.onnx")(observations)  # a recurrent policy: one sequence
    with owned_temporary_folder("embedrl-report-") as tmp:
        build.make("lib", export_dir / "c", Path(tmp))
        policy = build.CPolicy(Path(tmp) / "libpolicy.so", export["name"], export["observation_dim"],
                               export["action_dim"])  # fmt: skip
        policy.reset()
        actions, codes = policy.batch(observations)
    diff = np.abs(actions.astype(np.float64) - expected)
    errors = np.max(diff, axis=1)
    row.update(samples=len(errors), errors=errors, generated_c=IDENTICAL)
    row["max_error"], row["p99_error"] = float(errors.max()), float(np.percentile(errors, 99))
    row["max_ulp"] = verify.max_ulp(actions, np.asarray(expected, dtype=np.float32))
    if export.get("quantize"):
        model = quantize.evaluate(again.graph, observations, again.section)
        a32, m32 = np.ascontiguousarray(actions, np.float32), np.ascontiguousarray(model, np.float32)
        row["bit_exact_with_model"] = bool(np.array_equal(a32.view(np.uint32), m32.view(np.uint32)))
        row["passed"] = row["bit_exact_with_model"] and not np.any(codes)
    else:
        tolerance = float(export["verification"]["tolerance"])
        within = diff <= tolerance * np.maximum(1.0, np.abs(expected))
        row["passed"] = bool(np.all(within)) and not np.any(codes)
    return row


def coverage(
    export_dir: Path,
    export: dict[str, Any],
    row: dict[str, Any],
    hils: Sequence[tuple[Path, str, dict[str, Any]]] = (),
) -> dict[str, Any] | str:
    """The deployed C's coverage (:mod:`embedrl.hil.signoff.coverage`) with this export's policy, whose C
    runs on this host only once ``row`` (its :func:`recompute`) found it to be the generator's, merged with
    the profiles of the HIL reports ``hils`` (path, name on the page, data) made with coverage; each other
    HIL report is named with why it was not merged (``hil_not_merged``; ``failed``: its recorded profile is
    missing or changed). Where coverage cannot be measured, one line saying why."""
    from embedrl.export.errors import BuildError
    from embedrl.export.regenerate import OBSERVATIONS
    from embedrl.hil import coverage as recorded
    from embedrl.hil.signoff import coverage as measured

    if row["generated_c"] != IDENTICAL:
        return f"the policy's C is not the generator's ({row['generated_c']}): not run on this host"
    observations = np.load(export_dir / OBSERVATIONS, allow_pickle=False).astype(np.float32)
    merged, not_merged = [], []
    for report, name, data in hils:
        try:
            binary, profiles = recorded.sources(report, data)
        except HilError as exc:
            not_merged.append({"report": name, "why": str(exc), "failed": bool(data.get("coverage"))})
            continue
        left_out = len(data["coverage"].get("unreadable", []))
        compiler = data["coverage"].get("compiler")
        merged.append(measured.HilProfile(name, binary, tuple(profiles), left_out, compiler))
    try:
        summary = measured.measure(export_dir / "c", export["name"], observations, tuple(merged))
    except BuildError as exc:
        return str(exc).strip().splitlines()[-1]
    except (OSError, ValueError, KeyError, IndexError, TypeError) as exc:
        return f"llvm-cov's output could not be read: {exc}"
    summary["hil_not_merged"] = not_merged
    return summary


def image_memory(elf: Path) -> dict[str, Any]:
    """Bytes per section (``arm-none-eabi-size -A``) and the largest symbols (``readelf -s``); an image
    that is no ELF file is refused in one line."""
    with elf.open("rb") as f:
        if f.read(len(ELF_MAGIC)) != ELF_MAGIC:
            raise HilError(f"{elf}: not an ELF image (export it again to rebuild it)")
    sizes = subprocess.run(["arm-none-eabi-size", "-A", str(elf)], capture_output=True, text=True)
    if sizes.returncode != 0:
        why = (sizes.stderr.strip().splitlines() or ["no output"])[-1]
        raise HilError(f"{elf}: arm-none-eabi-size cannot read it ({why})")
    sections = {}
    for line in sizes.stdout.splitlines():
        parts = line.split()
        if len(parts) == 3 and parts[0] in SECTIONS:
            sections[parts[0]] = int(parts[1])
    table = subprocess.run(["arm-none-eabi-readelf", "-sW", str(elf)], capture_output=True, text=True)
    if table.returncode != 0:
        why = (table.stderr.strip().splitlines() or ["no output"])[-1]
        raise HilError(f"{elf}: arm-none-eabi-readelf cannot read it ({why})")
    symbols: list[dict[str, Any]] = []
    for line in table.stdout.splitlines():
        parts = line.split()
        if len(parts) == 8 and parts[3] in ("FUNC", "OBJECT") and parts[2].isdigit() and int(parts[2]) > 0:
            in_ram = int(parts[1], 16) >= RAM_ORIGIN
            kind = "code" if parts[3] == "FUNC" else ("RAM" if in_ram else "constant (flash)")
            symbols.append({"symbol": parts[7], "bytes": int(parts[2]), "kind": kind, "at": parts[1]})
    symbols.sort(key=lambda s: (-s["bytes"], s["symbol"]))
    by_address: dict[str, dict[str, Any]] = {}  # aliases (__aeabi_dadd, __adddf3) share one: listed once
    for symbol in symbols:
        by_address.setdefault(symbol["at"], symbol)
    symbols = list(by_address.values())
    return {"sections": sections, "symbols": symbols[:TOP_SYMBOLS]}


def target_facts(
    export: dict[str, Any], export_dir: Path, hils: list[dict[str, Any]]
) -> list[dict[str, Any]]:
    """Per Cortex-M target: the export's measurements, memory per section and symbol, the stack bounds
    beside what was painted (the test image's policy_step; the firmware node in a HIL run)."""
    rows = []
    for name, t in export.get("targets", {}).items():
        node_runs = [h for h in hils if _on_firmware(h) and h.get("target") == name]
        peaks = [
            h["firmware"]["stack_peak_bytes"] for h in node_runs if h["firmware"].get("stack_peak_bytes")
        ]
        images = {}
        for image in ("node.elf", "firmware.elf"):
            elf = export_dir / "bin" / name / image
            if elf.is_file():
                images[image] = image_memory(elf)
        rows.append({
            "target": name,
            "measured": t,
            "images": images,
            "node_stack_peak_bytes": max(peaks, default=None),
            "node_step": next((h["time_on_target"] for h in node_runs if h.get("time_on_target")), None),
        })  # fmt: skip
    return rows


def closed_loop_rows(export: dict[str, Any], hils: list[tuple[str, dict[str, Any]]]) -> list[dict[str, Any]]:
    """Outcomes per platform on the same seeds: the simulation with onnxruntime and with the C (the
    export's check), then each HIL run beside the simulation on its own seeds."""
    rows = []
    loop = export.get("closed_loop") or {}
    for key, label in (("reference", "simulation, onnxruntime"), ("c", "simulation, generated C")):
        if key in loop:
            rows.append(_outcomes(label, loop[key], loop.get("seed"), None))
    for name, h in hils:
        where = f"HIL, {h['node']} node" + (f" on {h['target']}" if h.get("target") else "")
        row = _outcomes(f"{where} ({name})", h, h.get("seed"), h["verdict"]["passed"])
        rows.append({**row, **_hil_facts(h)})
        if h.get("simulation"):
            rows.append(_outcomes(f"simulation, same seeds ({name})", h["simulation"], h.get("seed"), None))
    return rows


Z95 = 1.959963984540054
"""The standard normal quantile of a two-sided 95% interval."""


def wilson(successes: int, episodes: int) -> tuple[float, float]:
    """The Wilson score 95% interval of a success rate: what ``successes`` of ``episodes`` says of the rate
    (3 of 3 reads 0.44-1.00, 200 of 200 0.98-1.00)."""
    if episodes <= 0:
        return 0.0, 1.0
    p = successes / episodes
    centre = (p + Z95**2 / (2 * episodes)) / (1 + Z95**2 / episodes)
    half = Z95 * math.sqrt(p * (1 - p) / episodes + Z95**2 / (4 * episodes**2)) / (1 + Z95**2 / episodes)
    return max(0.0, centre - half), min(1.0, centre + half)


def _success_text(data: dict[str, Any]) -> str | None:
    successes, episodes = data.get("successes"), data.get("episodes")
    if not isinstance(successes, int) or not isinstance(episodes, int) or episodes <= 0:
        return None
    low, high = wilson(successes, episodes)
    return f"{successes} of {episodes} ({successes / episodes:.0%}; 95% interval {low:.0%}-{high:.0%})"


def _hil_facts(h: dict[str, Any]) -> dict[str, Any]:
    """Where a HIL run ran and its three questions kept apart: the node matches the simulation (actions and
    outcomes), it meets the sample time (round trip p99), the task succeeds (every episode)."""
    sandbox = h.get("sandbox") or "host kernel"
    place = {"uml": "User-Mode Linux on the host (vcan)", "qemu": "a QEMU guest (vcan)"}.get(
        str(sandbox), str(sandbox)
    )
    if _on_firmware(h):
        place = f"QEMU ({h.get('target')}) bridged over SLCAN to {place}"
    p99_us = (h.get("latency_us") or {}).get("p99")
    sample_s = h.get("sample_time_s")
    meets = None if p99_us is None or not sample_s else p99_us <= 1e6 * sample_s
    differing = h.get("outcomes_differing_from_simulation") or []
    return {
        "where": f"{place}; no physical hardware",
        "matches_simulation": not differing and bool(h["verdict"]["passed"]),
        "meets_sample_time": meets,
        "task_succeeds": h.get("successes") == h.get("episodes"),
    }


def _outcomes(label: str, data: dict[str, Any], seed: Any, passed: bool | None) -> dict[str, Any]:
    keys = ("episodes", "successes", "collisions", "timeouts")
    return {"platform": label, "seed": seed, "verdict": passed, "success": _success_text(data),
            **{k: data.get(k) for k in keys}}  # fmt: skip
