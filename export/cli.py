"""``embedrl export``: the export package's subcommands."""

from __future__ import annotations

import argparse
import math
import sys
from pathlib import Path
from typing import Any

from embedrl.common import on_terminal, read_json, table
from embedrl.export.errors import ExportError
from embedrl.export.target import TARGETS
from embedrl.train import arguments
from embedrl.train.arguments import add_export_dir_argument, add_model_file_arguments, add_scenario_argument
from embedrl.train.scenarios import DEFAULT_SCENARIO

EMX_IN_CHECKOUT = Path(__file__).resolve().parents[1] / "tools" / "emx" / "bin" / "emx-onnx-cgen"
"""Where ``make bench`` and ``make bench-target`` install emx-onnx-cgen: bench-target's peer, from any
working directory."""


def _safe_action(text: str) -> tuple[float, ...]:
    try:
        values = tuple(float(v) for v in text.split(","))
    except ValueError:
        raise argparse.ArgumentTypeError(f"expected comma-separated numbers, got {text!r}") from None
    if not all(abs(v) < float("inf") for v in values):
        raise argparse.ArgumentTypeError(f"safe action must be finite, got {text!r}")
    return values


def _ranges(text: str) -> tuple[tuple[float, float], ...]:
    """``LOW:HIGH`` (every value) or ``LOW:HIGH,LOW:HIGH,...`` (one per value)."""
    try:
        pairs = tuple(tuple(float(x) for x in part.split(":")) for part in text.split(","))
    except ValueError:
        raise argparse.ArgumentTypeError(f"expected LOW:HIGH[,LOW:HIGH...], got {text!r}") from None
    if any(len(p) != 2 for p in pairs):
        raise argparse.ArgumentTypeError(f"expected LOW:HIGH[,LOW:HIGH...], got {text!r}")
    return tuple((p[0], p[1]) for p in pairs)


MAX_MODEL_MB = 4096.0
"""The largest --max-model-mb: a limit, not a way to switch limits off."""
MAX_PARAMS = 1_000_000_000


def _model_mb(text: str) -> float:
    try:
        value = float(text)
    except ValueError:
        value = math.nan
    if not 0 < value <= MAX_MODEL_MB:  # NaN and inf fail too
        raise argparse.ArgumentTypeError(
            f"expected a size in MB within (0, {MAX_MODEL_MB:.0f}], got {text!r}"
        )
    return value


def _param_count(text: str) -> int:
    try:
        value = int(text)
    except ValueError:
        value = 0
    if not 1 <= value <= MAX_PARAMS:
        raise argparse.ArgumentTypeError(f"expected a count within 1..{MAX_PARAMS:,}, got {text!r}")
    return value


QUANTIZE_METAVAR = "{int8,int8-weights,q15}"
"""The schemes of ``--quantize`` as its help lists them (:data:`embedrl.export.quantize.SCHEMES`)."""


def _scheme(text: str) -> str:
    """A ``--quantize`` scheme; a former name is taken as the scheme it now names, with a one-line note."""
    from embedrl.export.quantize import RENAMED, SCHEMES

    if text in RENAMED:
        print(f"note: --quantize {text} is now --quantize {RENAMED[text]}", file=sys.stderr)
        return RENAMED[text]
    if text not in SCHEMES:
        raise argparse.ArgumentTypeError(f"invalid choice: {text!r} (choose from {', '.join(SCHEMES)})")
    return text


def _tolerance(text: str) -> float:
    try:
        value = float(text)
    except ValueError:
        value = math.nan
    if not 0 < value <= 1e-2:
        raise argparse.ArgumentTypeError(f"expected a tolerance within (0, 0.01], got {text!r}")
    return value


def _names(path: Path | None) -> dict[str, Any] | None:
    if path is None:
        return None
    try:
        names = read_json(path)
    except (OSError, ValueError) as exc:
        raise ExportError(f"--names {path}: not a readable JSON file ({exc})") from None
    if not isinstance(names, dict):
        raise ExportError(f'--names {path}: expected {{"observation": [...], "action": [...]}}')
    return names


def _env_id(args: argparse.Namespace) -> str:
    from embedrl.train.scenarios import SCENARIOS

    if args.env is not None and args.scenario is not None:
        raise ExportError("give --env or --scenario, not both")
    return args.env or SCENARIOS[args.scenario or DEFAULT_SCENARIO].env_id


def cmd_export(args: argparse.Namespace) -> int:
    from embedrl.export import chain, signature
    from embedrl.export.onnx_import import Limits
    from embedrl.export.pipeline import ExportOptions, run_export

    key = signature.load_private_key(args.sign) if args.sign else None  # a bad key before any work
    opts = ExportOptions(
        source=args.source,
        out=args.out,
        name=args.name,
        env_id=_env_id(args),
        episodes=args.episodes,
        seed=args.seed,
        vecnormalize=args.vecnormalize,
        trust_pickle=args.trust_pickle,
        safe_action=args.safe_action,
        force=args.force,
        targets=tuple(args.target or ()),
        quantize=args.quantize,
        progress=on_terminal(),
        limits=Limits(max_bytes=int(args.max_model_mb * 2**20), max_parameters=args.max_params),
        obs_range=args.obs_range,
        act_range=args.act_range,
        sample_time=args.sample_time,
        names=_names(args.names),
        names_file=args.names,
        tolerance=args.tolerance,
    )
    report = run_export(opts)
    _print_summary(report)
    kept = sorted(str(p.relative_to(args.out)) for p in (args.out / "bin").rglob("*") if p.is_file())
    written = [*report["files"], *kept, "export_report.json", chain.MANIFEST]
    if key is not None:
        signature.sign(args.out, key)
        written.append(signature.ENVELOPE)
    print(f"wrote {args.out}/ ({', '.join(written)})")
    return 0


def cmd_verify_chain(args: argparse.Namespace) -> int:
    """Exit 0 when every link matches and the signature is valid or absent (and no key was given), 1 at the
    first link that does not match (named) or a signature that does not hold, 2 without a manifest or with a
    bad key file."""
    from embedrl.export import chain, signature

    public_key = signature.load_public_key(args.key) if args.key else None
    checks = chain.verify(args.export_dir)
    for number, check in enumerate(checks, 1):
        if args.verbose or not check.ok:
            state = "ok  " if check.ok else "FAIL"
            print(f"{state} link {number}/{len(checks)} {check.link.name}: {check.detail}")
        if not check.ok:
            return 1
    outside = sum(not c.link.in_bundle for c in checks)
    print(
        f"chain intact: {len(checks)} links, from {checks[0].link.name} to {checks[-1].link.name}"
        + (f" ({outside} outside the bundle, digest only)" if outside else "")
    )
    signed = signature.check(args.export_dir, public_key)
    label = "FAIL " if not signed.passed else "" if signed.verified else "warning: "
    print(f"{label}signature: {signed.detail}")
    return 0 if signed.passed else 1


def _quantization_rows(report: dict[str, Any]) -> list[tuple[str, str]]:
    """The summary's lines on a quantised export: scheme, bit-exactness, distance from its reference."""
    v = report["verification"]
    q = v["quantization"]
    rows = [
        ("quantization", q["scheme"]),
        ("C vs Python model of it", f"{q['model_mismatches']} of {v['samples']} samples differ in any bit"),
    ]
    qdq = q.get("qdq")
    if qdq is None:
        rows.append((f"worst |{report['quantize']} - float|", f"{q['worst_action_error_vs_float']:.3g}"))
        return rows
    rows.append(("worst |C - QDQ model| (action)", f"{q['worst_action_error_vs_float']:.3g}"))
    steps = ", ".join(f"{s:.2g}" for s in qdq["max_layer_steps"])
    rows.append(
        (
            "layers vs QDQ model",
            f"max steps {steps} (input, then each layer; allowed {qdq['tolerance_steps']:g}); "
            f"end to end {qdq['end_to_end_max_output_steps']:.2f} output steps",
        )
    )
    return rows


def _print_summary(report: dict[str, Any]) -> None:
    v = report["verification"]
    rows = [
        ("source", f"{report['source']['path']} ({report['source']['policy_class'] or 'ONNX'})"),
        ("ops", " ".join(report["ops"])),
        ("samples (from rollouts)", f"{v['samples']} ({v['samples_from_rollouts']})"),
    ]
    if v["onnx_vs_sb3_max_abs_error"] is not None:
        rows.append(("max |ONNX - SB3|", f"{v['onnx_vs_sb3_max_abs_error']:.3g}"))
    if "quantization" in v:
        rows += _quantization_rows(report)
    else:
        rows.append(("max |C - onnxruntime|", f"{v['c_vs_onnxruntime_max_abs_error']:.3g}"))
    nan = v.get("nan_propagation")
    if nan is not None:
        integer = f", {nan['integer_ops']} in integers" if nan.get("integer_ops") else ""
        rows.append(("NaN propagation", f"{nan['ops']} ops, {nan['positions']} positions as ONNX{integer}"))
    loop = report["closed_loop"]
    if "skipped" in loop:
        rows.append(("closed loop", f"skipped: {loop['skipped']}"))
    else:
        for who in ("reference", "c"):
            r = loop[who]
            rows.append(
                (
                    f"closed loop {who}",
                    f"{r['successes']} / {r['collisions']} / {r['timeouts']} (success / collision / timeout)",
                )
            )
        rows.append(("episodes with another outcome", f"{loop['differing_outcomes']} of {loop['episodes']}"))
        rows.append(("max |C - reference| on C's path", f"{loop['c_trajectory_max_action_diff']:.3g}"))
    for name, t in report["targets"].items():
        check = (
            "bit-exact with the model"
            if t["bit_exact_with_model"]
            else f"max |error| {t['max_abs_error']:.3g}"
        )
        rows.append((f"{name} on QEMU {t['qemu_machine']}", check))
        rows.append(
            (
                f"{name} policy size",
                f"flash {t['flash_bytes']} B, RAM {t['ram_bytes']} B "
                f"(stack {t['stack_bytes']} B measured, {t['stack_bound']['bytes']} B bound); "
                f"test image flash {t['image_flash_bytes']} B",
            )
        )
        node = t["node_firmware"]
        rows.append(
            (
                f"{name} firmware node",
                f"flash {node['flash_bytes']:,} B, RAM {node['image_ram_bytes']:,} B; stack bound "
                f"{node['stack_bound']['bytes']} B (one cycle and the deepest interrupt)",
            )
        )
        share = t["fraction_of_sample_time"]
        rows.append(
            (
                f"{name} time per inference",
                f"{t['instructions_per_inference']:,.0f} instructions (measured), "
                f"~{t['estimated_cycles_per_inference']:,} cycles (model) = "
                f"{t['estimated_inference_us']:,.0f} us on {t['clock']['part']}"
                + (f", {100 * share:.2g}% of the sample time" if share is not None else ""),
            )
        )
    size = report["code_size"]
    rows.append(("object size", f"text {size['text']} B, data {size['data']} B, bss {size['bss']} B"))
    print(table(rows))


def cmd_bench_target(args: argparse.Namespace) -> int:
    from embedrl.common import read_json, table, write_json
    from embedrl.export import target, target_comparison

    if not (args.export_dir / "policy.onnx").is_file():
        raise ExportError(f"{args.export_dir}: no policy.onnx (give an `embedrl export` folder)")
    quantize = read_json(args.export_dir / "export_report.json").get("quantize") or "float32"
    emx = args.emx if quantize == "float32" else None
    if emx is None:
        print(f"{quantize}: measured alone (emx-onnx-cgen generates float32 C; see the float32 export's run)")
    report = target_comparison.run(args.export_dir, args.target or list(target.TARGETS), emx)
    rows: list[tuple[str, str]] = []
    for t in report["targets"]:
        for who in ("embedrl", "emx_onnx_cgen")[: 1 if emx is None else 2]:
            f = t[who]
            rows.append((
                f"{t['target']} {who} {quantize if who == 'embedrl' else 'float32'}: instructions / "
                "est. cycles (per multiply-add) / flash",
                f"{f['instructions_per_inference']:,.0f} / {f['estimated_cycles_per_inference']:,} "
                f"({f['estimated_cycles_per_multiply_add']}) / {f['flash_bytes']:,} B",
            ))  # fmt: skip
        if emx is None:
            continue
        ratios = f"{t['ratio_instructions']}x instructions, {t['ratio_cycles']}x cycles"
        agree = f"actions agree within {t['max_action_difference']:.2g}"
        rows.append((f"{t['target']} emx / embedrl", f"{ratios} ({agree})"))
    print(table(rows))
    if args.json:
        write_json(report, args.json)
        print(f"wrote {args.json}")
    return 0


def cmd_bench_export(args: argparse.Namespace) -> int:
    from embedrl.common import print_measurement
    from embedrl.export.inference_latency import run

    print_measurement(run(args.export_dir, args.seed, args.emx, args.float32_dir), args.json)
    return 0


def register(sub: Any) -> None:
    """Add the export subcommands to the ``embedrl`` parser."""
    p = sub.add_parser("export", help="SB3 model or ONNX -> ONNX + generated C, verified")
    p.add_argument("source", type=Path, help="SB3 model (.zip) or ONNX file (.onnx)")
    p.add_argument(
        "--out", "--export-dir", type=Path, required=True, metavar="EXPORT_DIR",
        help="the export folder to write (written atomically; every other command reads it)",
    )  # fmt: skip
    p.add_argument("--name", default="policy", help="symbol prefix and file name of the generated C")
    p.add_argument(
        "--env",
        help="gymnasium environment for samples and closed loop (default: the --scenario's env)",
    )
    add_scenario_argument(p, default=None)  # None: static, unless --env names another env
    p.add_argument("--episodes", type=int, default=200, help="closed-loop episodes (0 skips)")
    p.add_argument("--seed", type=arguments.seed, default=0, help="the verification's samples and episodes")
    add_model_file_arguments(p)
    p.add_argument(
        "--safe-action",
        type=_safe_action,
        help="what the policy writes on non-finite input and the CAN node sends when it cannot trust "
        "its input, "
        "e.g. 0,0 (default: the scenario's safe action)",
    )
    p.add_argument(
        "--obs-range",
        type=_ranges,
        help="a policy without an env: its observation ranges, LOW:HIGH for all or LOW:HIGH,... per value "
        "(with --act-range and --sample-time; --env is then unused and the closed loop skipped)",
    )
    p.add_argument("--act-range", type=_ranges, help="a policy without an env: its action ranges")
    p.add_argument("--sample-time", type=float, help="a policy without an env: its control period in seconds")
    p.add_argument(
        "--names",
        type=Path,
        help='JSON {"observation": [...], "action": [...]}: names for the interface\'s fields '
        "(default: the scenario's names; obs0.., act0.. for envs without a spec)",
    )
    p.add_argument("--force", action="store_true", help="replace a non-empty output folder")
    _add_precision_arguments(p)
    p.set_defaults(func=cmd_export)

    p = sub.add_parser(
        "verify-chain",
        help="recompute every hash of an export's traceability chain; name the first link that changed",
    )
    add_export_dir_argument(p, "an `embedrl export` folder (with chain.json)")
    p.add_argument("--verbose", action="store_true", help="one line per link")
    p.add_argument(
        "--key", type=Path, metavar="PUBLIC.pem",
        help="check the chain's signature with this Ed25519 public key (PEM); an unsigned export then fails",
    )  # fmt: skip
    p.set_defaults(func=cmd_verify_chain)

    _register_benchmarks(sub)


def _add_precision_arguments(p: Any) -> None:
    """``export``'s signature, verification tolerance, model limits, precision and targets."""
    p.add_argument(
        "--sign", type=Path, metavar="PRIVATE.pem",
        help="sign the traceability chain with this Ed25519 private key (PEM, `openssl genpkey -algorithm "
        "ed25519`): chain.dsse.json",
    )  # fmt: skip
    p.add_argument(
        "--tolerance",
        type=_tolerance,
        default=1e-5,
        help="allowed error between export steps, times max(1, |output|)",
    )
    p.add_argument(
        "--max-model-mb",
        type=_model_mb,
        default=64.0,
        help="refuse models larger than this, external data included",
    )
    p.add_argument(
        "--max-params",
        type=_param_count,
        default=4_000_000,
        help="refuse models with more weights",
    )
    p.add_argument(
        "--quantize",
        type=_scheme,
        metavar=QUANTIZE_METAVAR,
        help="int8: int8 weights and activations, int32 sums (DSP instructions on Cortex-M4/M7); "
        "int8-weights: int8 weights per output channel, float activations (recurrent policies too); "
        "q15: 16-bit fixed point (no FPU)",
    )
    p.add_argument(
        "--target",
        action="append",
        choices=tuple(TARGETS),
        help="also build firmware for this Cortex-M, run it on QEMU and measure it (repeatable)",
    )


def _register_benchmarks(sub: Any) -> None:
    """``bench-export`` (inference time on this machine) and ``bench-target`` (on the Cortex-M cores)."""
    p = sub.add_parser("bench-export", help="ns per inference: generated C vs onnxruntime vs torch")
    add_export_dir_argument(p, "an export folder (default: the study's 6-100-100-2 actor)", needed=False)
    p.add_argument(
        "--seed", type=arguments.seed, default=0, help="the study actor's weights and the observations timed"
    )
    p.add_argument(
        "--emx", type=Path, help="emx-onnx-cgen's command: its C timed as a peer (make bench: tools/emx)"
    )
    p.add_argument(
        "--float32-dir", type=Path, metavar="FLOAT32_EXPORT_DIR",
        help="the float32 export of the same policy, for a quantised EXPORT_DIR: both timed in the same "
        "harness in turn, their ratio printed (c_ratio_to_float32)",
    )  # fmt: skip
    p.add_argument("--json", type=Path, help="write the measurement here")
    p.set_defaults(func=cmd_bench_export)

    p = sub.add_parser(
        "bench-target", help="instructions and cycles per inference on Cortex-M: embedrl vs emx-onnx-cgen"
    )
    add_export_dir_argument(p, "an `embedrl export` folder")
    p.add_argument(
        "--target", action="append", choices=tuple(TARGETS), default=[],
        help="a Cortex-M target, repeatable (default: every one)",
    )  # fmt: skip
    p.add_argument(
        "--emx", type=Path, default=EMX_IN_CHECKOUT,
        help="emx-onnx-cgen's command (default: the checkout's; make bench-target installs it)",
    )  # fmt: skip
    p.add_argument("--json", type=Path, help="write the measurement here")
    p.set_defaults(func=cmd_bench_target)


ERRORS: tuple[type[Exception], ...] = (ExportError,)
"""Exceptions the dispatcher reports as one-line errors."""
