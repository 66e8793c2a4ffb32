"""The firmware node on the HIL bus: the Cortex-M image (``make -C runtime_c TARGET=... node``) on
``qemu-system-arm``, its UART0 on a pseudo-terminal carrying CAN frames as SLCAN lines, bridged to the bus.

The route: harness -> ``vcan0`` -> bridge -> python-can ``slcan`` on the pty -> QEMU's UART0 -> firmware
(``runtime_c/cortex_m/transport_uart.c``), and the action frames back the same way. The bridge is two
threads in the session process: python-can's ``slcan`` interface (what a serial CAN adapter's host side
runs) and a SocketCAN socket filtered to the node's observation IDs, as the C node's socket is, so the bus
sees the same frames, IDs and E2E fields as with the host node. It needs no kernel module beyond vcan, so it
runs wherever the host node runs (can-utils' ``slcand`` would need the guest's ``slcan`` driver and a
gateway rule per direction).

QEMU runs with ``-icount shift=0``: virtual time advances 1 ns per guest instruction, so the timer the
firmware reads counts instructions (:data:`INSTRUCTIONS_PER_TICK` per tick at the boards' 25 MHz). The
firmware writes one line per answered step on its diagnostics UART (UART1, a file here):
``S <step> <ticks>`` from the last observation frame in to the action frame out, and after each status
frame ``X <overflows> <bad lines> <peak stack bytes>``.
"""

from __future__ import annotations

import contextlib
import re
import subprocess
import threading
import time
from collections.abc import Callable
from pathlib import Path
from typing import Any

import can
import numpy as np

from embedrl.hil.errors import HilError
from embedrl.hil.nodes import Node

BOARD_CLOCK_HZ = 25_000_000
"""The MPS2 boards' timer clock (runtime_c/cortex_m/board.h)."""
ICOUNT_SHIFT = 0
INSTRUCTIONS_PER_TICK = 1e9 / BOARD_CLOCK_HZ / 2**ICOUNT_SHIFT
"""Guest instructions per timer tick under ``-icount shift=0`` (1 ns of virtual time per instruction)."""
PTY_TIMEOUT_S = 30.0
STOP_TIMEOUT_S = 5.0
DIAG_QUIET_S = 0.2
"""The diagnostics file is complete once it has not grown for this long (the firmware writes a step's line
just after that step's action frame, so the last line can trail the last answer)."""
BRIDGE_POLL_S = 0.01
_PTY = re.compile(r"char device redirected to (/dev/pts/\d+)")
_STEP = re.compile(r"^S (\d+) (\d+)$")
_STATUS = re.compile(r"^X (\d+) (\d+) (\d+)$")


class FirmwareNode(Node):
    """The firmware image on QEMU, bridged to ``iface`` (python-can interface ``bus``)."""

    def __init__(
        self, elf: str, machine: str, open_bus: Callable[[], can.BusABC], diag: Path, receive_ids: list[int]
    ) -> None:
        """``open_bus``: a new socket on the harness's bus (the bridge's side of it); ``receive_ids``: the
        node's observation IDs, the only frames the bridge carries to the firmware."""
        self.elf, self.machine, self.open_bus, self.diag = elf, machine, open_bus, diag
        self.receive_ids = receive_ids
        self.starts = 0
        self._start()

    def _diag_path(self, start: int) -> Path:
        return self.diag.with_name(f"{self.diag.stem}-{start}{self.diag.suffix}")

    def _start(self) -> None:
        diag = self._diag_path(self.starts)
        self.starts += 1
        self.process = subprocess.Popen(
            ["qemu-system-arm", "-M", self.machine, "-nographic", "-monitor", "none", "-semihosting",
             "-icount", f"shift={ICOUNT_SHIFT}", "-serial", "pty", "-serial", f"file:{diag}",
             "-kernel", self.elf],
            stdout=subprocess.PIPE, stderr=subprocess.STDOUT, text=True,
        )  # fmt: skip
        assert self.process.stdout is not None
        first = self.process.stdout.readline()
        found = _PTY.search(first)
        if found is None:
            self.process.kill()
            raise HilError(f"qemu-system-arm gave the firmware's UART no pseudo-terminal: {first.strip()}")
        self.serial = can.Bus(interface="slcan", channel=found.group(1), sleep_after_open=0)
        self.bus = self.open_bus()
        self.bus.set_filters([{"can_id": i, "can_mask": 0x7FF, "extended": False} for i in self.receive_ids])
        self.running = True
        self.threads = [
            threading.Thread(target=self._carry, args=(self.bus, self.serial), daemon=True),
            threading.Thread(target=self._carry, args=(self.serial, self.bus), daemon=True),
        ]
        for thread in self.threads:
            thread.start()

    def _carry(self, source: can.BusABC, sink: can.BusABC) -> None:
        """Frames from ``source`` to ``sink`` until the node stops (a closed end ends the direction)."""
        while self.running:
            try:
                msg = source.recv(BRIDGE_POLL_S)
                if msg is not None:
                    sink.send(msg)
            except (can.CanError, OSError, ValueError):
                if self.running and self.alive():
                    continue  # the bus refused one frame (a full queue): the node's E2E counts it
                return

    def _end_bridge(self) -> None:
        self.running = False
        for thread in self.threads:
            thread.join(timeout=STOP_TIMEOUT_S)
        for end in (self.serial, self.bus):
            with contextlib.suppress(can.CanError, OSError):  # the pty is gone with QEMU
                end.shutdown()

    def alive(self) -> bool:
        return self.process.poll() is None

    def exit_reason(self) -> str:
        return f"the firmware's QEMU exited with status {self.process.returncode}"

    def kill(self) -> None:
        self.process.kill()
        self.process.wait()
        self._end_bridge()

    def _let_diagnostics_settle(self) -> None:
        """Wait (at most :data:`STOP_TIMEOUT_S`) until the running firmware's diagnostics file has been quiet
        for :data:`DIAG_QUIET_S`."""
        path = self._diag_path(self.starts - 1)
        deadline = time.monotonic() + STOP_TIMEOUT_S
        size, quiet_since = -1, time.monotonic()
        while time.monotonic() < deadline and self.alive():
            now_size = path.stat().st_size if path.is_file() else 0
            if now_size != size:
                size, quiet_since = now_size, time.monotonic()
            elif time.monotonic() - quiet_since >= DIAG_QUIET_S:
                return
            time.sleep(DIAG_QUIET_S / 4)

    def stop(self) -> None:
        if self.process.poll() is None:
            self._let_diagnostics_settle()
            self.process.terminate()
            try:
                self.process.wait(timeout=STOP_TIMEOUT_S)
            except subprocess.TimeoutExpired:
                self.process.kill()
                self.process.wait()
        self._end_bridge()

    def restart(self) -> None:
        self.stop()
        self._start()

    def step_instructions(self) -> list[float]:
        """Instructions of every answered step so far (last observation frame in -> action frame out), in
        the order the firmware answered them, over all its starts."""
        counts: list[float] = []
        for start in range(self.starts):
            path = self._diag_path(start)
            if path.is_file():
                for line in path.read_text(errors="replace").splitlines():
                    match = _STEP.match(line.strip())
                    if match:
                        counts.append(int(match.group(2)) * INSTRUCTIONS_PER_TICK)
        return counts

    def stack_peak(self) -> int | None:
        """The deepest stack the firmware painted and found used, in bytes, over all its starts (None before
        its first status line)."""
        peaks = [
            int(match.group(3))
            for start in range(self.starts)
            if self._diag_path(start).is_file()
            for line in self._diag_path(start).read_text(errors="replace").splitlines()
            if (match := _STATUS.match(line.strip()))
        ]
        return max(peaks, default=None)


def instruction_summary(counts: list[float]) -> dict[str, Any] | None:
    """Mean, median, max and count of per-step instruction counts (None without any)."""
    if not counts:
        return None
    values = np.asarray(counts)
    return {
        "steps": len(counts),
        "mean": float(values.mean()),
        "p50": float(np.median(values)),
        "max": float(values.max()),
        "resolution": INSTRUCTIONS_PER_TICK,
    }
