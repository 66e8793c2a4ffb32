"""The firmware node on the HIL bus: the Cortex-M image (``make -C runtime_c TARGET=... node``) on
``qemu-system-arm``, its UART0 on a pseudo-terminal carrying CAN frames as SLCAN lines, bridged to the bus.

The route: harness -> ``vcan0`` -> bridge -> python-can ``slcan`` on the pty -> QEMU's UART0 -> firmware
(``runtime_c/cortex_m/transport_uart.c``), and the action frames back the same way. The bridge is two
threads in the session process: python-can's ``slcan`` interface (what a serial CAN adapter's host side
runs) and a SocketCAN socket filtered to the node's observation IDs, as the C node's socket is, so the bus
sees the same frames, IDs and E2E fields as with the host node. It needs no kernel module beyond vcan, so it
runs wherever the host node runs (can-utils' ``slcand`` would need the guest's ``slcan`` driver and a
gateway rule per direction).

The firmware's clock is the simulation's (``runtime_c/cortex_m/clock_sim.c``): the session lets time pass
for it with :meth:`FirmwareNode.advance`, a time line (``Y`` and the microseconds in hex) on the serial
line before each step's observation and while a fault keeps the bus quiet; the firmware answers ``Y`` once
it has acted on the new time. Its watchdog and status period therefore count simulated time: a slow or
busy host delays the run, never its verdict.

QEMU runs with ``-icount shift=0``: virtual time advances 1 ns per guest instruction, so the timer the
firmware reads counts instructions (the target's ``tick_instructions`` per tick: 1 on the STM32F405's TIM2,
40 on the MPS2 boards' 25 MHz timer). The
firmware writes one line per answered step on its diagnostics UART (UART1, a file here):
``S <step> <ticks>`` from the last observation frame in to the action frame out, and after each status
frame ``X <overflows> <bad lines> <peak stack bytes>``.

Where QEMU runs (:class:`Emulator`): beside the bridge (:class:`LocalQemu`, UART0 on a pseudo-terminal), or,
when the sandbox is a User-Mode Linux guest, on the host (:class:`HostQemu`, served by :func:`serve_qemu`
in the ``hil run`` process): inside UML every QEMU system call is a ptrace round trip, so the emulator ran
its frames 50-100x slower and its idle clock, which follows the host's, made a busy host look like a
silent bus. On the host, UART0 is the host end of the guest's serial line (:attr:`Guest.link`,
``/dev/ttyS1`` in the guest) and the session asks for starts, kills and stops through request files in a
folder both see (``<n>.start`` holding the diagnostics path, ``<n>.kill``, ``<n>.stop``; answered with
``<n>.started`` and ``<n>.exit`` holding QEMU's exit status).
"""

from __future__ import annotations

import contextlib
import os
import re
import select
import socket
import subprocess
import threading
import time
from abc import ABC, abstractmethod
from collections.abc import Callable, Iterator
from pathlib import Path
from typing import Any

import can
import numpy as np
from can.interfaces.slcan import slcanBus

from embedrl.export.contract.layout import STATUS_PERIOD_MS
from embedrl.hil.errors import HilError
from embedrl.hil.nodes import PolicyNode

ICOUNT_SHIFT = 0
"""1 ns of virtual time per guest instruction."""
PTY_TIMEOUT_S = 30.0
STOP_TIMEOUT_S = 5.0
DIAG_QUIET_S = 0.2
"""The diagnostics file is complete once it has not grown for this long (the firmware writes a step's line
just after that step's action frame, so the last line can trail the last answer)."""
BRIDGE_POLL_S = 0.01
REQUEST_POLL_S = 0.005
"""How often the host's QEMU server looks for the session's requests (and the session for the answers)."""
TIME_LINE_MAX_US = 0xFFFFFFFF
"""The largest advance one time line carries (8 hex digits); a longer one is sent in parts."""
TIME_ANSWER_TIMEOUT_S = 10.0
"""How long the bridge waits for the firmware to answer a time line while its QEMU runs (a loaded host
may be slow; a QEMU that exits ends the wait at once)."""
TIME_ANSWER = "Y"
LISTEN_POLL_S = 0.2
"""While the firmware starts, a time line of 0 us is sent this often until it answers."""
_PTY = re.compile(r"char device redirected to (/dev/pts/\d+)")
_STEP = re.compile(r"^S (\d+) (\d+)$")
_STATUS = re.compile(r"^X (\d+) (\d+) (\d+)$")


def qemu_argv(machine: str, elf: str, uart0: str, diag: Path) -> list[str]:
    """QEMU's command line: the image on ``machine``, UART0 on the character device ``uart0`` (``pty``,
    ``chardev:ID``), UART1 into the file ``diag``."""
    return ["qemu-system-arm", "-M", machine, "-nographic", "-monitor", "none", "-semihosting",
            "-icount", f"shift={ICOUNT_SHIFT}", "-serial", uart0, "-serial", f"file:{diag}",
            "-kernel", elf]  # fmt: skip


def _let_diagnostics_settle(path: Path, alive: Callable[[], bool]) -> None:
    """Wait (at most :data:`STOP_TIMEOUT_S`) until a running firmware's diagnostics file has been quiet for
    :data:`DIAG_QUIET_S` (the firmware writes a step's line just after that step's action frame)."""
    deadline = time.monotonic() + STOP_TIMEOUT_S
    size, quiet_since = -1, time.monotonic()
    while time.monotonic() < deadline and alive():
        now_size = path.stat().st_size if path.is_file() else 0
        if now_size != size:
            size, quiet_since = now_size, time.monotonic()
        elif time.monotonic() - quiet_since >= DIAG_QUIET_S:
            return
        time.sleep(DIAG_QUIET_S / 4)


def _end(process: subprocess.Popen[str], diag: Path | None) -> None:
    """End QEMU: in order once ``diag`` is complete, or at once (None)."""
    if process.poll() is None and diag is not None:
        _let_diagnostics_settle(diag, lambda: process.poll() is None)
        process.terminate()
        with contextlib.suppress(subprocess.TimeoutExpired):
            process.wait(timeout=STOP_TIMEOUT_S)
    if process.poll() is None:
        process.kill()
    process.wait()


class Emulator(ABC):
    """Where the firmware's QEMU runs, and the serial device through which the bridge reaches its UART0."""

    @abstractmethod
    def start(self, diag: Path) -> str:
        """Start the image (UART1 into ``diag``); the serial device the bridge opens."""

    @abstractmethod
    def alive(self) -> bool: ...

    @abstractmethod
    def exit_status(self) -> int | None: ...

    @abstractmethod
    def kill(self) -> None:
        """End QEMU at once (a crash)."""

    @abstractmethod
    def stop(self, diag: Path) -> None:
        """End QEMU in order, once its diagnostics file ``diag`` is complete."""


class LocalQemu(Emulator):
    """QEMU as a child of this process, UART0 on a pseudo-terminal."""

    def __init__(self, elf: str, machine: str) -> None:
        self.elf, self.machine = elf, machine
        self.process: subprocess.Popen[str] | None = None

    def start(self, diag: Path) -> str:
        self.process = subprocess.Popen(
            qemu_argv(self.machine, self.elf, "pty", diag),
            stdout=subprocess.PIPE, stderr=subprocess.STDOUT, text=True,
        )  # fmt: skip
        assert self.process.stdout is not None
        first = self.process.stdout.readline()
        found = _PTY.search(first)
        if found is None:
            self.kill()
            raise HilError(f"qemu-system-arm gave the firmware's UART no pseudo-terminal: {first.strip()}")
        return found.group(1)

    def alive(self) -> bool:
        return self.process is not None and self.process.poll() is None

    def exit_status(self) -> int | None:
        return None if self.process is None else self.process.returncode

    def kill(self) -> None:
        if self.process is not None:
            _end(self.process, None)

    def stop(self, diag: Path) -> None:
        if self.process is not None:
            _end(self.process, diag)


class HostQemu(Emulator):
    """QEMU on the host, started, killed and stopped by :func:`serve_qemu` at this session's request (files
    in ``control``); UART0 is the guest's serial line ``device``."""

    def __init__(self, control: Path, device: str) -> None:
        self.control, self.device = control, device
        self.n = -1

    def _request(self, kind: str, text: str = "") -> None:
        partial = self.control / f".{self.n}.{kind}"
        partial.write_text(text)
        partial.rename(self.control / f"{self.n}.{kind}")  # the server only sees complete requests

    def _await(self, kind: str, timeout_s: float) -> None:
        deadline = time.monotonic() + timeout_s
        while not (self.control / f"{self.n}.{kind}").is_file():
            if time.monotonic() > deadline:
                raise HilError(f"the host's QEMU server gave no {kind!r} within {timeout_s:.0f} s")
            time.sleep(REQUEST_POLL_S)

    def start(self, diag: Path) -> str:
        self.n += 1
        self._request("start", str(diag))
        self._await("started", PTY_TIMEOUT_S)
        return self.device

    def alive(self) -> bool:
        return self.n >= 0 and not (self.control / f"{self.n}.exit").is_file()

    def exit_status(self) -> int | None:
        found = self.control / f"{self.n}.exit"
        return int(found.read_text() or "-1") if found.is_file() else None

    def kill(self) -> None:
        if self.alive():
            self._request("kill")
            self._await("exit", STOP_TIMEOUT_S)

    def stop(self, diag: Path) -> None:
        if self.alive():
            self._request("stop")
            self._await("exit", 3 * STOP_TIMEOUT_S)


@contextlib.contextmanager
def serve_qemu(elf: str, machine: str, link: socket.socket, control: Path) -> Iterator[None]:
    """Run the firmware's QEMU on this machine for a session in a guest: a thread answers the
    :class:`HostQemu` requests in ``control`` (one QEMU at a time, its UART0 on ``link``, the host end of the
    guest's serial line) until the block ends; a QEMU still running then is killed."""
    control.mkdir(parents=True, exist_ok=True)
    done = threading.Event()
    thread = threading.Thread(target=_serve, args=(elf, machine, link, control, done), daemon=True)
    thread.start()
    try:
        yield
    finally:
        done.set()
        thread.join()


def _drain(link: socket.socket) -> None:
    """Drop what the guest wrote while no QEMU listened (a closing bridge's lines)."""
    link.setblocking(False)
    try:
        while link.recv(4096):
            pass
    except BlockingIOError:
        pass
    finally:
        link.setblocking(True)


def _answer(control: Path, name: str, text: str = "") -> None:
    partial = control / f".{name}"
    partial.write_text(text)
    partial.rename(control / name)


def _serve(elf: str, machine: str, link: socket.socket, control: Path, done: threading.Event) -> None:
    """The server's loop: request ``n`` starts QEMU number ``n`` (any earlier one killed first)."""
    n, diag = -1, Path()
    process: subprocess.Popen[str] | None = None

    def finish(settled: Path | None) -> None:
        nonlocal process
        assert process is not None
        _end(process, settled)
        _answer(control, f"{n}.exit", str(process.returncode))
        process = None

    try:
        while not done.is_set():
            if (control / f"{n + 1}.start").is_file():
                if process is not None:
                    finish(None)
                n += 1
                diag = Path((control / f"{n}.start").read_text())
                _drain(link)
                argv = qemu_argv(machine, elf, "chardev:link", diag)
                argv[1:1] = ["-chardev", f"socket,id=link,fd={link.fileno()}"]
                process = subprocess.Popen(
                    argv, pass_fds=(link.fileno(),), stdout=subprocess.DEVNULL, text=True
                )
                _answer(control, f"{n}.started")
            elif process is not None and (control / f"{n}.kill").is_file():
                finish(None)
            elif process is not None and (control / f"{n}.stop").is_file():
                finish(diag)
            elif process is not None and process.poll() is not None:
                finish(None)  # QEMU ended by itself: the session sees the exit
            else:
                time.sleep(REQUEST_POLL_S)
    finally:
        if process is not None:
            _end(process, None)


class SerialLine(slcanBus):
    """python-can's ``slcan`` interface (python-can 4.6) reading its serial device in blocks: one ``select``
    and one ``read`` per burst of lines, where python-can polls and reads byte by byte (in a User-Mode
    Linux guest each system call is a ptrace round trip: ~60 per frame made the bridge the slowest part of
    the loop), and writing a line without waiting for the device to drain it."""

    TERMINATORS = (slcanBus._OK[0], slcanBus._ERROR[0])

    def __init__(self, *args: Any, **kwargs: Any) -> None:
        self._writing = threading.Lock()  # the bridge's thread and the session both write lines
        self._answers = threading.Condition()
        self._time_answers = 0
        super().__init__(*args, **kwargs)

    def tell_time(self, us: int, alive: Callable[[], bool], timeout_s: float = TIME_ANSWER_TIMEOUT_S) -> bool:
        """Send the time line advancing the firmware's clock by ``us``; True once the firmware answered
        (read by the bridge's thread: every frame the firmware sent before the answer is on the bus)."""
        with self._answers:
            wanted = self._time_answers + 1
        self._write(f"{TIME_ANSWER}{us:X}")
        deadline = time.monotonic() + timeout_s
        with self._answers:
            while self._time_answers < wanted:
                if not alive() or time.monotonic() > deadline:
                    return False
                self._answers.wait(BRIDGE_POLL_S)
        return True

    def _read(self, timeout: float | None) -> str | None:
        line = self._read_line(timeout)
        if line is not None and line.startswith(TIME_ANSWER):
            with self._answers:
                self._time_answers += 1
                self._answers.notify_all()
        return line

    def _read_line(self, timeout: float | None) -> str | None:
        fd = self.serialPortOrig.fileno()
        deadline = None if timeout is None else time.monotonic() + timeout
        while True:
            end = next((i for i, byte in enumerate(self._buffer) if byte in self.TERMINATORS), None)
            if end is not None:
                line = self._buffer[: end + 1].decode(errors="replace")
                del self._buffer[: end + 1]
                return line
            left = None if deadline is None else max(0.0, deadline - time.monotonic())
            if not select.select([fd], [], [], left)[0]:
                return None
            chunk = os.read(fd, 4096)
            if not chunk:
                return None
            self._buffer.extend(chunk)

    def _write(self, string: str) -> None:
        with self._writing:
            self.serialPortOrig.write(string.encode() + self.LINE_TERMINATOR)


class FirmwareNode(PolicyNode):
    """The firmware image on QEMU, bridged to ``iface`` (python-can interface ``bus``); its clock is the
    simulation's (:meth:`advance`)."""

    simulated_time = True

    def __init__(
        self,
        elf: str,
        machine: str,
        open_bus: Callable[[], can.BusABC],
        diag: Path,
        receive_ids: list[int],
        emulator: Emulator | None = None,
        tick_instructions: float = 1.0,
    ) -> None:
        """``open_bus``: a new socket on the harness's bus (the bridge's side of it); ``receive_ids``: the
        node's observation IDs, the only frames the bridge carries to the firmware; ``emulator``: where
        QEMU runs (None: :class:`LocalQemu`, beside the bridge); ``tick_instructions``: guest instructions
        per tick of the board's timer (the target's)."""
        self.tick_instructions = tick_instructions
        self.elf, self.machine, self.open_bus, self.diag = elf, machine, open_bus, diag
        self.receive_ids = receive_ids
        self.emulator = emulator or LocalQemu(elf, machine)
        self.starts = 0
        self._start()

    def _diag_path(self, start: int) -> Path:
        return self.diag.with_name(f"{self.diag.stem}-{start}{self.diag.suffix}")

    def _start(self) -> None:
        diag = self._diag_path(self.starts)
        self.starts += 1
        device = self.emulator.start(diag)
        self.serial = SerialLine(channel=device, sleep_after_open=0)
        self.bus = self.open_bus()
        self.bus.set_filters([{"can_id": i, "can_mask": 0x7FF, "extended": False} for i in self.receive_ids])
        self.running = True
        self.threads = [
            threading.Thread(target=self._carry, args=(self.bus, self.serial), daemon=True),
            threading.Thread(target=self._carry, args=(self.serial, self.bus), daemon=True),
        ]
        for thread in self.threads:
            thread.start()
        self._await_listening()
        # The firmware starts its node once the channel is open (transport_await_open), so its first status
        # reaches the bus; a status period of simulated time brings the next one, the sign that its clock
        # follows the time lines.
        self.advance(STATUS_PERIOD_MS / 1000)

    def _await_listening(self) -> None:
        """Wait until the firmware answers a time line of 0 us, then open its channel ('O') again: a UART
        that the firmware has not enabled yet drops what arrives (the STM32's USART does), and the bridge's
        first 'O' may have come that early."""
        deadline = time.monotonic() + PTY_TIMEOUT_S
        while not self.serial.tell_time(0, self.alive, LISTEN_POLL_S):
            if not self.alive() or time.monotonic() > deadline:
                return  # the first step then goes unanswered, and the session says why
        self.serial.open()

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
        return self.emulator.alive()

    def advance(self, seconds: float) -> bool:
        """Time lines for ``seconds`` of the simulation's time (in parts of at most
        :data:`TIME_LINE_MAX_US`), each answered before the next goes out; False if one is not (the firmware
        is gone or hung: the step it was for then goes unanswered)."""
        left = round(seconds * 1e6)
        while left > 0 and self.running:
            part = min(left, TIME_LINE_MAX_US)
            if not self.serial.tell_time(part, self.alive):
                return False
            left -= part
        return self.running

    def exit_reason(self) -> str:
        return f"the firmware's QEMU exited with status {self.emulator.exit_status()}"

    def kill(self) -> None:
        self.emulator.kill()
        self._end_bridge()

    def stop(self) -> None:
        self.emulator.stop(self._diag_path(self.starts - 1))
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
                        counts.append(int(match.group(2)) * self.tick_instructions)
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


def instruction_summary(counts: list[float], resolution: float) -> dict[str, Any] | None:
    """Mean, median, max and count of per-step instruction counts, each read to ``resolution`` instructions
    (None without any)."""
    if not counts:
        return None
    values = np.asarray(counts)
    return {
        "steps": len(counts),
        "mean": float(values.mean()),
        "p50": float(np.median(values)),
        "max": float(values.max()),
        "resolution": resolution,
    }
