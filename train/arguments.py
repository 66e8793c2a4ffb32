"""Command-line options several commands share (train, eval, render, bench, shaping, export), defined once."""

from __future__ import annotations

import argparse
from pathlib import Path

from embedrl.train.scenarios import DEFAULT_SCENARIO, SCENARIOS, scenario_help

PORTABLE_HELP = (
    "the same result on any x86-64 CPU (MKL's compatible code path, PyTorch's generic kernels; about 1.6x "
    "slower); without it the same seed repeats on the same kind of CPU"
)


def add_scenario_argument(p: argparse.ArgumentParser, default: str | None = DEFAULT_SCENARIO) -> None:
    """``--scenario``: which of the scenarios (None as default: the command tells it from elsewhere)."""
    p.add_argument("--scenario", choices=tuple(SCENARIOS), default=default, help=scenario_help())


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
        help="the model's normalisation statistics (.npz, or SB3's .pkl read without running code); "
        "default: found beside the model, RL Zoo's <env>/vecnormalize.pkl included",
    )
