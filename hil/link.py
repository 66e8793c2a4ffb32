"""The simulator's end of the bus: send observation frames, collect actions and status, log every frame.

Works on any python-can bus (:class:`can.BusABC`): SocketCAN ``vcan0`` for the verdict, python-can's
virtual bus for fast tests of the session logic.
"""

from __future__ import annotations

import time
from collections.abc import Callable
from dataclasses import dataclass, field

import can
import numpy as np

from embedrl.export.contract.layout import STEP_MODULO
from embedrl.hil.codec import Action, Codec, Diag, Status

ALIVE_POLL_S = 0.05
"""While waiting for an action, how often to ask whether the node is still running."""


@dataclass
class Stats:
    frames_tx: int = 0
    frames_rx: int = 0
    rx_timeouts: int = 0
    latencies_us: list[float] = field(default_factory=list)
    exchanges: list[tuple[int, np.ndarray, np.ndarray]] = field(default_factory=list)
    """Every answered step: its Step counter, the observation the node decoded, the node's action (compared
    with the reference when the episodes are over: :mod:`embedrl.hil.compare`)."""
    episode_starts: list[int] = field(default_factory=list)
    """Where in :attr:`exchanges` each episode begins (a policy with memory starts again there)."""
    deadline_misses: int = 0
    step_starts: list[list[float]] = field(default_factory=list)
    """Real time: when each step's observation went out (monotonic seconds), per episode."""
    last_status: Status | None = None
    last_status_time: float = 0.0
    last_diag: Diag | None = None
    snapshots: list[tuple[float, Status, Diag]] = field(default_factory=list)
    """Every NodeStatus with the NodeDiag after it, and when the pair arrived (monotonic seconds)."""
    retries: int = 0
    """Observations sent again because their action did not come within the retry interval."""
    send_failures: int = 0
    """Frames the simulator's own interface refused (e.g. while the link is down)."""
    actions_by_step: dict[int, int] = field(default_factory=dict)
    """How many complete actions arrived per Step value (a duplicate answer shows as 2)."""

    @staticmethod
    def merged(parts: list[Stats]) -> Stats:
        """The links of several nodes as one: counts added, samples joined (each node's recorded steps stay
        with its own link)."""
        out = Stats()
        for part in parts:
            out.frames_tx += part.frames_tx
            out.frames_rx += part.frames_rx
            out.rx_timeouts += part.rx_timeouts
            out.retries += part.retries
            out.send_failures += part.send_failures
            out.latencies_us += part.latencies_us
        out.last_status, out.last_diag = parts[0].last_status, parts[0].last_diag
        return out


class Link:
    """Frames out and in through ``bus``, decoded with ``codec``, counted in ``stats``, logged to ``log``."""

    def __init__(
        self,
        bus: can.BusABC,
        codec: Codec,
        stats: Stats,
        channel: str,
        log: str | None,
        logger: can.Listener | None = None,
    ) -> None:
        """``log``: a file to log every frame to; or ``logger``, one shared with other links (not stopped
        by :meth:`close`)."""
        self.bus = bus
        self.codec = codec
        self.stats = stats
        self.channel = channel
        self.log = logger or (can.Logger(log) if log else None)
        self.owns_log = logger is None
        self.received_at = 0.0
        """When the last frame :meth:`receive` returned reached this machine's socket (``time.time()``
        seconds: the kernel's receive time on SocketCAN), not when this process got to read it."""

    def send(self, frames: list[can.Message]) -> None:
        stamp = time.time() if self.log else 0.0  # only the log shows it: no clock read without one
        for frame in frames:
            frame.timestamp = stamp
            frame.channel = self.channel
            frame.is_rx = False
            try:
                self.bus.send(frame)
            except can.CanError:
                self.stats.send_failures += 1  # link down: the frame is lost, as on a real bus
                continue
            self.stats.frames_tx += 1
            if self.log:
                self.log(frame)

    def receive(self, timeout_s: float) -> Action | Status | Diag | bool | None:
        """One frame within ``timeout_s``, decoded (None: not ours or not valid); False if none came."""
        try:
            msg = self.bus.recv(timeout=max(timeout_s, 0.0))
        except can.CanError:  # the interface went down: nothing can arrive until it is back
            time.sleep(max(timeout_s, 0.0))
            return False
        if msg is None:
            return False
        self.received_at = msg.timestamp or time.time()
        # python-can flags frames from another local socket (the node) as Tx; they are received here.
        msg.is_rx = True
        msg.channel = self.channel
        self.stats.frames_rx += 1
        if self.log:
            self.log(msg)
        decoded = self.codec.decode(msg)
        if isinstance(decoded, Status):
            self.stats.last_status, self.stats.last_status_time = decoded, time.monotonic()
        elif isinstance(decoded, Diag):
            self.stats.last_diag = decoded
            if self.stats.last_status is not None:
                self.stats.snapshots.append((time.monotonic(), self.stats.last_status, decoded))
        elif isinstance(decoded, Action):
            self.stats.actions_by_step[decoded.step] = self.stats.actions_by_step.get(decoded.step, 0) + 1
        return decoded

    def wait_action(
        self, step: int, until: float, alive: Callable[[], bool] | None = None, now: float | None = None
    ) -> Action | None:
        """Drain the bus until the action for ``step`` arrives or ``until`` (``time.monotonic`` seconds)
        passes; stop early once ``alive()`` says the node is gone (checked every :data:`ALIVE_POLL_S` of
        silence). ``now``: a clock reading just taken (the step's send time), so that the common case, the
        action as the next frame, reads no clock here (under UML every clock read is a system call)."""
        if now is None:
            now = time.monotonic()
        while (remaining := until - now) > 0:
            decoded = self.receive(min(remaining, ALIVE_POLL_S) if alive else remaining)
            if isinstance(decoded, Action) and decoded.step == step % STEP_MODULO:
                return decoded
            if decoded is False and alive is not None and not alive():
                return None
            now = time.monotonic()
        return None

    def wait_status(self, timeout_s: float) -> Status | None:
        deadline = time.monotonic() + timeout_s
        while (remaining := deadline - time.monotonic()) > 0:
            decoded = self.receive(remaining)
            if decoded is False:
                return None
            if isinstance(decoded, Status):
                return decoded
        return None

    def snapshot(self, timeout_s: float) -> tuple[Status, Diag] | None:
        """The node's next NodeStatus and the NodeDiag sent with it (None if they do not come)."""
        deadline = time.monotonic() + timeout_s
        status = None
        while (remaining := deadline - time.monotonic()) > 0:
            decoded = self.receive(remaining)
            if decoded is False:
                return None
            if isinstance(decoded, Status):
                status = decoded
            elif isinstance(decoded, Diag) and status is not None:
                return status, decoded
        return None

    def drain(self, seconds: float) -> None:
        """Receive (and count) whatever arrives for ``seconds``."""
        deadline = time.monotonic() + seconds
        while (remaining := deadline - time.monotonic()) > 0:
            if self.receive(remaining) is False:
                return

    def close(self) -> None:
        if self.log and self.owns_log:
            self.log.stop()
        self.bus.shutdown()
