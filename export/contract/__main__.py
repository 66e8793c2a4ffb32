"""``python -m embedrl.export.contract``: a policy's CAN database and node C, or its frames as a table.

``(--scenario NAME | --interface FILE) [--out DIR] [--markdown] [--dbc-only] [--use-float] [--nodes N]
[--fd]``. ``embedrl export`` writes the same files into the export folder (``can/``, ``can-fd/``); this
command is for a database of several nodes on one bus, a float-only codec, or a look at the frames.
"""

from __future__ import annotations

import argparse
import sys
from pathlib import Path

from embedrl.export.contract.dbc import markdown_table
from embedrl.export.contract.interface_file import load_interface
from embedrl.export.contract.layout import MAX_NODES
from embedrl.export.contract.sources import write
from embedrl.train.scenarios import SCENARIOS


def main(argv: list[str] | None = None) -> int:
    parser = argparse.ArgumentParser(
        prog="python -m embedrl.export.contract", description=(__doc__ or "").split("\n")[0]
    )
    source = parser.add_mutually_exclusive_group(required=True)
    source.add_argument("--scenario", choices=sorted(SCENARIOS))
    source.add_argument("--interface", type=Path, help="an export's interface.json")
    parser.add_argument("--out", type=Path, help="write the DBC and the node's C here")
    parser.add_argument("--markdown", action="store_true", help="print the frames and signals as a table")
    parser.add_argument("--dbc-only", action="store_true")
    parser.add_argument("--nodes", type=int, default=1, help=f"nodes on one bus (1..{MAX_NODES})")
    parser.add_argument(
        "--fd", action="store_true", help="observations and actions in CAN FD frames (64 bytes)"
    )
    parser.add_argument(
        "--use-float", action="store_true", help="scale signals in float (cores without double-precision FPU)"
    )
    args = parser.parse_args(argv)
    try:
        interface = SCENARIOS[args.scenario] if args.scenario else load_interface(args.interface)
        if args.markdown:
            print(markdown_table(interface), end="")
        if args.out is not None:
            write(interface, args.out, args.dbc_only, args.use_float, args.nodes, args.fd)
        elif not args.markdown:
            parser.error("give --out DIR, --markdown or both")
    except (ValueError, OSError) as exc:  # ContractError and InterfaceError are ValueErrors
        print(f"error: {exc}", file=sys.stderr)
        return 2
    return 0


if __name__ == "__main__":
    sys.exit(main())
