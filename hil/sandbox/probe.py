"""The sandbox self-test: an ``AF_CAN`` raw socket on the interface, one frame sent and received back.

Run as ``python -m embedrl.hil.sandbox.probe IFACE`` inside the guest; exit status 0 means SocketCAN works
there. Standard library only, so it also runs before the project's dependencies are installed.
"""

from __future__ import annotations

import socket
import struct
import sys

FRAME = struct.Struct("=IB3x8s")
"""struct can_frame: 32-bit ID, length, padding, 8 data bytes."""
PROBE_ID = 0x7DF
PROBE_DATA = b"embedrl!"
TIMEOUT_S = 5.0


def probe(iface: str) -> str:
    """Send a frame on ``iface`` from one raw socket and receive it on another; describe the result."""
    try:
        tx = socket.socket(socket.AF_CAN, socket.SOCK_RAW, socket.CAN_RAW)
        rx = socket.socket(socket.AF_CAN, socket.SOCK_RAW, socket.CAN_RAW)
    except OSError as exc:
        raise SystemExit(f"no AF_CAN socket: {exc}") from None
    with tx, rx:
        try:
            rx.bind((iface,))
            tx.bind((iface,))
        except OSError as exc:
            raise SystemExit(f"cannot bind to {iface}: {exc}") from None
        rx.settimeout(TIMEOUT_S)
        frame = FRAME.pack(PROBE_ID, len(PROBE_DATA), PROBE_DATA)
        tx.send(frame)
        try:
            got = rx.recv(FRAME.size)
        except TimeoutError:
            raise SystemExit(f"a frame sent on {iface} did not come back within {TIMEOUT_S} s") from None
        if got != frame:
            raise SystemExit(f"a frame sent on {iface} came back changed: {got.hex()}")
    return f"AF_CAN ok: a frame sent on {iface} came back"


if __name__ == "__main__":
    print(probe(sys.argv[1] if len(sys.argv) > 1 else "vcan0"))
