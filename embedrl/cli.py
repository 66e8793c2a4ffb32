"""The ``embedrl`` command: every package's subcommands, registered explicitly.

``train`` adds ``eval``, ``render``, ``train``, ``bench``, ``bench-env``; ``export`` adds ``export`` and
``bench-export``; ``hil`` adds ``hil run`` and ``hil doctor``. Errors a package raises on purpose (its
``ERRORS``) print as one line ``error: ...`` with exit status 2; ``--debug`` shows the traceback.
SIGINT and SIGTERM stop a command in order (its temporary folders removed, its children stopped): one
line ``interrupted``, exit status 130 (SIGINT) or 143 (SIGTERM).
"""

from __future__ import annotations

import argparse
import json
import signal
import sys
import threading
import traceback
from types import FrameType
from typing import NoReturn

from embedrl import __version__
from embedrl.common import check_output
from embedrl.export import cli as export_cli
from embedrl.hil import cli as hil_cli
from embedrl.train import cli as train_cli

PACKAGES = (train_cli, export_cli, hil_cli)
OUTPUTS = (("json", False), ("log", False), ("plot", True))
"""Output options of any command, and whether the option names a folder (``--plot`` of ``hil run``;
``--plot`` of ``eval`` is a file)."""
COMMON_ERRORS: tuple[type[Exception], ...] = (OSError, ValueError, json.JSONDecodeError)


class Parser(argparse.ArgumentParser):
    """argparse with its usage errors as one line (``embedrl train: error: ...``), exit status 2."""

    def error(self, message: str) -> NoReturn:
        self.exit(2, f"{self.prog}: error: {message} (see {self.prog} --help)\n")


def build_parser() -> argparse.ArgumentParser:
    parser = Parser(prog="embedrl", description=(__doc__ or "").splitlines()[0] if __doc__ else None)
    parser.add_argument("--version", action="version", version=f"embedrl {__version__}")
    parser.add_argument("--debug", action="store_true", help="show tracebacks")
    sub = parser.add_subparsers(dest="command", required=True, metavar="COMMAND")
    for package in PACKAGES:
        package.register(sub)
    return parser


class Terminated(KeyboardInterrupt):
    """SIGTERM, raised where the command is, so that its clean-up runs as for Ctrl-C."""


STOP_SIGNALS = (signal.SIGINT, signal.SIGTERM)


def _stop(signum: int, frame: FrameType | None) -> None:
    """The first SIGINT or SIGTERM raises where the command is; any later one is ignored, so that a
    second Ctrl-C cannot cut the clean-up short (which is bounded: guests and nodes are killed, not
    waited for) and leave a guest or a node running."""
    for s in STOP_SIGNALS:
        signal.signal(s, signal.SIG_IGN)
    raise Terminated if signum == signal.SIGTERM else KeyboardInterrupt


def main(argv: list[str] | None = None) -> int:
    args = build_parser().parse_args(argv)
    args.argv = list(sys.argv[1:] if argv is None else argv)
    args.as_command = argv is None  # the process is this command (it may start itself again)
    handled = COMMON_ERRORS + tuple(e for package in PACKAGES for e in package.ERRORS)
    main_thread = threading.current_thread() is threading.main_thread()  # only it may set handlers
    previous = {s: signal.signal(s, _stop) for s in STOP_SIGNALS} if main_thread else {}
    try:
        for option, folder in OUTPUTS:
            path = getattr(args, option, None)
            if path is not None:  # checked before any work: a run's results are never lost at the end
                check_output(path, f"--{option}", folder=folder and args.command == "hil")
        return int(args.func(args))
    except handled as exc:
        if args.debug:
            traceback.print_exc()
        print(f"error: {exc}", file=sys.stderr)
        return 2
    except KeyboardInterrupt as exc:
        print("interrupted", file=sys.stderr)
        return 128 + (signal.SIGTERM if isinstance(exc, Terminated) else signal.SIGINT)
    finally:
        for s, handler in previous.items():
            signal.signal(s, handler)


if __name__ == "__main__":
    sys.exit(main())
