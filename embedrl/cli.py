"""The ``embedrl`` command: every package's subcommands, registered explicitly.

``train`` adds ``eval``, ``render``, ``train``, ``bench``, ``bench-env``; ``export`` adds ``export`` and
``bench-export``; ``hil`` adds ``hil run`` and ``hil doctor``. Errors a package raises on purpose (its
``ERRORS``) print as one line ``error: ...`` with exit status 2; ``--debug`` shows the traceback.
"""

from __future__ import annotations

import argparse
import json
import sys
import traceback

from embedrl import __version__
from embedrl.export import cli as export_cli
from embedrl.hil import cli as hil_cli
from embedrl.train import cli as train_cli

PACKAGES = (train_cli, export_cli, hil_cli)
COMMON_ERRORS: tuple[type[Exception], ...] = (OSError, ValueError, json.JSONDecodeError)


def build_parser() -> argparse.ArgumentParser:
    parser = argparse.ArgumentParser(
        prog="embedrl", description=(__doc__ or "").splitlines()[0] if __doc__ else None
    )
    parser.add_argument("--version", action="version", version=f"embedrl {__version__}")
    parser.add_argument("--debug", action="store_true", help="show tracebacks")
    sub = parser.add_subparsers(dest="command", required=True, metavar="COMMAND")
    for package in PACKAGES:
        package.register(sub)
    return parser


def main(argv: list[str] | None = None) -> int:
    args = build_parser().parse_args(argv)
    handled = COMMON_ERRORS + tuple(e for package in PACKAGES for e in package.ERRORS)
    try:
        return int(args.func(args))
    except handled as exc:
        if args.debug:
            traceback.print_exc()
        print(f"error: {exc}", file=sys.stderr)
        return 2


if __name__ == "__main__":
    sys.exit(main())
