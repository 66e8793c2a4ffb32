"""The ``embedrl`` command: every package's subcommands, registered explicitly.

``train`` adds ``eval``, ``render``, ``train``, ``bench``, ``bench-env``, ...; ``export`` adds ``export``,
``verify-chain``, ``bench-export``, ``bench-target``; ``hil`` adds ``hil run``, ``hil doctor`` and ``report``.
Errors a package raises on purpose (its ``ERRORS``) print as one line ``error: ...`` with exit status 2;
``--debug`` shows the traceback. SIGINT and SIGTERM stop a command in order (its temporary folders
removed, its children stopped): one line ``interrupted``, exit status 130 (SIGINT) or 143 (SIGTERM).
"""

from __future__ import annotations

import argparse
import copy
import json
import signal
import sys
import threading
import traceback
from collections.abc import Sequence
from types import FrameType
from typing import Any, NoReturn

from embedrl import __version__
from embedrl.common import check_output
from embedrl.export import cli as export_cli
from embedrl.hil import cli as hil_cli
from embedrl.train import cli as train_cli
from embedrl.train.arguments import EXPORT_DIR, ExportDirAction

PACKAGES = (train_cli, export_cli, hil_cli)
OUTPUTS = (("json", False), ("log", False), ("plot", True))
"""Output options of any command, and whether the option names a folder (``--plot`` of ``hil run``;
``--plot`` of ``eval`` is a file)."""
COMMON_ERRORS: tuple[type[Exception], ...] = (OSError, ValueError, json.JSONDecodeError)


DESCRIPTION = "A reinforcement-learning policy from simulation to a CAN controller, every step verified."
EPILOG = """the pipeline, in order:
  embedrl eval --controller potential-field --episodes 20    the baseline in simulation
  embedrl train --algo td3 --out out/run                      train a policy
  embedrl export policies/static/td3.zip --out out/td3        ONNX and C, verified
  embedrl hil run --export-dir out/td3                        the C policy as a CAN node in the loop
  embedrl report out/td3 --out out/td3.html                   the deployment report

each command's options: embedrl COMMAND --help"""


class HelpFormatter(argparse.RawDescriptionHelpFormatter):
    """Each option's default in its help, where it has one worth saying and the help does not already."""

    def _format_action(self, action: argparse.Action) -> str:
        if action.help is None and action.option_strings and _worth_saying(action.default):
            action = copy.copy(action)  # an option without help still shows its default
            action.help = "(default: %(default)s)"
        return super()._format_action(action)

    def _get_help_string(self, action: argparse.Action) -> str | None:
        text = action.help or ""
        default = action.default
        if "default" in text or not _worth_saying(default) or not action.option_strings:
            return text
        return f"{text} (default: %(default)s)"


def _worth_saying(default: object) -> bool:
    """A default the help should state (0 is one; no value, off and empty lists are not)."""
    return not (default is None or default is False or default is argparse.SUPPRESS or default in ([], ()))


class Parser(argparse.ArgumentParser):
    """argparse with whole option names only (``--ep`` is not ``--episodes``), defaults in the help, and
    usage errors as one line naming the (sub)command's help (``embedrl train: error: ...``), exit 2."""

    def __init__(self, *args: Any, **kwargs: Any) -> None:
        kwargs.setdefault("allow_abbrev", False)
        kwargs.setdefault("formatter_class", HelpFormatter)
        super().__init__(*args, **kwargs)

    def error(self, message: str) -> NoReturn:
        self.exit(2, f"{self.prog}: error: {message} (see {self.prog} --help)\n")

    def parse_known_args(  # type: ignore[override]
        self, args: Sequence[str] | None = None, namespace: argparse.Namespace | None = None
    ) -> tuple[argparse.Namespace, list[str]]:
        """argparse's, then: an export folder the command needs is given (either way it may be given)."""
        parsed, unknown = super().parse_known_args(args, namespace)
        for action in self._actions:
            if isinstance(action, ExportDirAction) and action.needed and getattr(parsed, action.dest) is None:
                self.error(f"the export folder is missing: give {EXPORT_DIR} or --export-dir {EXPORT_DIR}")
        return parsed, unknown


def build_parser() -> argparse.ArgumentParser:
    parser = Parser(prog="embedrl", description=DESCRIPTION, epilog=EPILOG)
    parser.add_argument("--version", action="version", version=f"embedrl {__version__}")
    parser.add_argument("--debug", action="store_true", help="show tracebacks")
    sub = parser.add_subparsers(dest="command", required=True, metavar="COMMAND")
    for package in PACKAGES:
        package.register(sub)
    return parser


def _parse(parser: argparse.ArgumentParser, argv: list[str] | None) -> argparse.Namespace:
    """Parse; an option no (sub)command knows is refused by the innermost subcommand, whose help it names."""
    args, unknown = parser.parse_known_args(argv)
    if unknown:
        innermost: argparse.ArgumentParser = parser
        for word in sys.argv[1:] if argv is None else argv:
            commands = [a for a in innermost._actions if isinstance(a, argparse._SubParsersAction)]
            if commands and word in commands[0].choices:
                innermost = commands[0].choices[word]
        innermost.error(f"unrecognized arguments: {' '.join(unknown)}")
    return args


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
    args = _parse(build_parser(), argv)
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
        # A caller in this process gets its handlers back; the command's own process keeps ignoring a
        # signal after the first until it has ended (a second Ctrl-C during its exit would end it by SIGINT,
        # not with 130).
        for s, handler in previous.items() if not args.as_command else ():
            signal.signal(s, handler)


if __name__ == "__main__":
    sys.exit(main())
