"""Command-line options several commands share (train, eval, render, bench, shaping, export, hil, report),
defined once."""

from __future__ import annotations

import argparse
from pathlib import Path
from typing import Any

from embedrl.train.errors import UsageError
from embedrl.train.scenarios import DEFAULT_SCENARIO, SCENARIOS, scenario_help

PORTABLE_HELP = (
    "the same result on any x86-64 CPU (MKL's compatible code path, PyTorch's generic kernels; about 1.6x "
    "slower); without it the same seed repeats on the same kind of CPU"
)


def add_scenario_argument(p: argparse.ArgumentParser, default: str | None = DEFAULT_SCENARIO) -> None:
    """``--scenario``: which of the scenarios (None as default: the command tells it from elsewhere, the
    default scenario unless something else says)."""
    said = "" if default is not None else f" (default: {DEFAULT_SCENARIO})"
    p.add_argument("--scenario", choices=tuple(SCENARIOS), default=default, help=scenario_help() + said)


def add_model_file_arguments(p: argparse.ArgumentParser) -> None:
    """``--trust-pickle`` and ``--vecnormalize``: how an SB3 model file and its statistics are opened
    (eval, render and export)."""
    p.add_argument(
        "--trust-pickle",
        action="store_true",
        help="open pickles inside or beside the model (SB3 fields, .pkl statistics): this runs code "
        "from them, so only for files you trust",
    )
    p.add_argument(
        "--vecnormalize",
        type=Path,
        help="the model's normalisation statistics (.npz, or SB3's .pkl read without running code) "
        "(default: found beside the model, RL Zoo's <env>/vecnormalize.pkl included)",
    )


MAX_SEED = 2**31 - 1
"""The largest ``--seed``: the seeds derived from it (an episode's seed + i, the seed bases of
:mod:`embedrl.common`) stay below 2^32, NumPy's and SB3's limit."""


def seed(text: str) -> int:
    """The type of every ``--seed``: a whole number 0..:data:`MAX_SEED` (Gymnasium and NumPy refuse a
    negative seed), refused at parsing in one line."""
    try:
        value = int(text)
    except ValueError:
        raise argparse.ArgumentTypeError(f"expected a whole number, got {text!r}") from None
    if not 0 <= value <= MAX_SEED:
        raise argparse.ArgumentTypeError(f"a seed is a whole number within 0..{MAX_SEED:,}, got {value}")
    return value


CONTROLLERS = ("potential-field",)
"""Built-in scripted controllers, usable wherever a policy is expected."""


def controller(name: str, scenario: str = DEFAULT_SCENARIO):  # type: ignore[no-untyped-def]
    from embedrl.train.potential_field import PotentialFieldController

    if name == "potential-field":
        return PotentialFieldController(scenario=scenario)
    raise UsageError(f"unknown controller {name!r}; available: {', '.join(CONTROLLERS)}")


def policy_from(args: argparse.Namespace):  # type: ignore[no-untyped-def]
    if args.model is not None:
        from embedrl.train.models import load_model_policy

        policy = load_model_policy(args.model, args.trust_pickle, args.vecnormalize)
        check_model_scenario(args)
        return policy
    if args.vecnormalize is not None:
        raise UsageError("--vecnormalize goes with a model, not with --controller")
    return controller(args.controller, args.scenario)


def env_id_of(args: argparse.Namespace) -> str:
    from embedrl.train.scenarios import SCENARIOS

    return SCENARIOS[args.scenario].env_id


def check_model_scenario(args: argparse.Namespace) -> None:
    """A model trained on one scenario's observation cannot run in another's: one clear line."""
    if args.model is None:
        return
    from embedrl.train.models import model_metadata
    from embedrl.train.scenarios import SCENARIOS

    meta = model_metadata(args.model) or {}
    trained = meta.get("scenario")
    if trained is not None and trained != args.scenario:
        raise UsageError(f"{args.model} was trained on scenario {trained}; pass --scenario {trained}")
    spec = SCENARIOS[args.scenario]
    shape = meta.get("observation_size")
    if shape is not None and shape != len(spec.observation):
        raise UsageError(
            f"{args.model} observes {shape} values but scenario {args.scenario} gives {len(spec.observation)}"
        )


def add_policy_arguments(p: argparse.ArgumentParser) -> None:
    add_scenario_argument(p)
    src = p.add_mutually_exclusive_group(required=True)
    src.add_argument("model", nargs="?", type=Path, help="a trained Stable-Baselines3 model (.zip)")
    src.add_argument("--controller", choices=CONTROLLERS, help="a built-in scripted controller")
    add_model_file_arguments(p)


EXPORT_DIR = "EXPORT_DIR"


class ExportDirAction(argparse.Action):
    """The export folder, given as a positional argument or as ``--export-dir`` (one destination, once).
    ``needed``: the command cannot run without it (``embedrl.cli.Parser`` checks that after parsing)."""

    def __init__(self, *args: Any, needed: bool = False, **kwargs: Any) -> None:
        super().__init__(*args, **kwargs)
        self.needed = needed

    def __call__(
        self,
        parser: argparse.ArgumentParser,
        namespace: argparse.Namespace,
        values: object,
        option_string: str | None = None,
    ) -> None:
        if values is None:  # the positional spelling, not given
            return
        if getattr(namespace, self.dest, None) is not None:
            parser.error(f"the export folder is given twice: give {EXPORT_DIR} or --export-dir {EXPORT_DIR}")
        setattr(namespace, self.dest, values)


def add_export_dir_argument(p: argparse.ArgumentParser, help: str, needed: bool = True) -> None:
    """The export folder a command reads, ``args.export_dir``: ``embedrl CMD DIR`` and ``embedrl CMD
    --export-dir DIR`` both work, in every command."""
    p.add_argument(
        "export_dir", nargs="?", type=Path, action=ExportDirAction, metavar=EXPORT_DIR, needed=needed,
        help=f"{help} (or --export-dir {EXPORT_DIR})",
    )  # fmt: skip
    p.add_argument(
        "--export-dir", dest="export_dir", type=Path, action=ExportDirAction, metavar=EXPORT_DIR,
        help="the same folder, as an option",
    )  # fmt: skip
