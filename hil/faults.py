"""Fault injection: a catalogue of injectors, a schedule saying when each strikes, and what each expects.

An injection replaces the normal sending of one step's observation (``NAME@EPISODE:STEP``, by default
at step :data:`INJECT_STEP` of the first episode). Around it the session takes the node's NodeStatus and
NodeDiag before and after, so every record says what was injected, whether the node *detected* it
(the counter the class must move moved) and whether the step was still *answered* (the simulator sends
an unanswered step again with fresh counters, see :mod:`embedrl.hil.session`).

``ends_episode``: the episode ends there as a fault (``injected: NAME``). ``detects``: the node counter
(a NodeStatus or NodeDiag field; ``a|b``: either) that must grow, ``node_exit`` when the simulator itself
sees the node die, ``bus_state`` when NodeDiag must report BUS_OFF, or None for the classes a node must
simply tolerate (reordered frames, a flood of foreign IDs). ``answered``: whether the step must still
get an action. ``needs_socketcan``: classes that act on the kernel interface (link down and up, error
frames) and cannot run on python-can's virtual bus.
"""

from __future__ import annotations

import shutil
import subprocess
import threading
import time
from abc import ABC, abstractmethod
from collections.abc import Callable
from dataclasses import dataclass, field
from pathlib import Path
from typing import TYPE_CHECKING, Any, ClassVar, cast

import numpy as np

from embedrl.common import system_tool
from embedrl.export.contract.layout import STATUS_PERIOD_MS, layout
from embedrl.hil import e2e

if TYPE_CHECKING:  # the command lists the injectors without loading the session's machinery
    import can

    from embedrl.hil.codec import Codec, Status
    from embedrl.hil.link import Link
    from embedrl.hil.nodes import PolicyNode
    from embedrl.train.interface import Interface

INJECT_STEP = 3
"""Where an injection strikes unless its schedule entry says otherwise."""
SILENCE_S = 5.0
"""How long the silent simulator listens for the node's safe action."""
BURST_FRAMES = 9
"""Frames lost per message in a burst: beyond the E2E forward window of 7, so the node must resync."""
LINK_DOWN_S = 0.3
"""How long the link stays down."""
FLOOD_MAX_S = 30.0
"""The foreign-ID flood lasts from its step to the end of the episode, at most this long."""
VIRTUAL_FLOOD_GAP_S = 0.0005
"""On python-can's virtual bus (no kernel filter: the reference node's thread sees every frame) the flood
is paced to at most 2,000 frames/s; on SocketCAN, can-utils' cangen sends as fast as the interface
takes frames."""
FLOOD_ID = 0x050
"""A foreign ID of higher priority than every one of the policy's."""
DELAY_FACTOR = 1.5
"""A delayed observation is held at least this many watchdog timeouts."""
DELAY_MAX_FACTOR = 10.0
"""... and on, at most this many, until the node reports its timeout: the watchdog runs on the node's clock,
which on a loaded machine can fall behind the host's (a node on the simulation's clock is held exactly
:data:`DELAY_FACTOR` timeouts of that time)."""
DELAY_POLL_FACTOR = 0.1
"""While held on, the bus is read in slices of this many watchdog timeouts."""
TIME_STEP_S = STATUS_PERIOD_MS / 1000
"""While a fault keeps the bus quiet, the simulation's time passes for the node in steps of this: the
resolution at which its reaction (the watchdog's safe action) is timed."""
SETTLE_S = 0.02
"""After a node on the simulation's clock acted on a time advance, what it sent is already on the bus: the
simulator reads until the bus has been quiet this long."""
CAN_ERR_CRTL, CAN_ERR_BUSOFF, CAN_ERR_RESTARTED = 0x04, 0x40, 0x100
CAN_ERR_CRTL_RX_PASSIVE = 0x10
"""Error-frame classes and the controller byte's passive flag (linux/can/error.h)."""


@dataclass
class Context:
    link: Link
    node: PolicyNode
    interface: Interface
    node_timeout_ms: int
    action_timeout_s: float
    bus_kind: str
    """python-can interface of the session (``socketcan`` or ``virtual``)."""
    iface: str
    previous: list[can.Message] | None = None
    """The frames of the previous step, as sent (for replays)."""
    at_episode_end: list[Callable[[], dict[str, Any]]] = field(default_factory=list)
    """What an injection leaves running until its episode ends; each returns what to add to its record."""

    @property
    def codec(self) -> Codec:
        return self.link.codec


class Injector(ABC):
    name: ClassVar[str]
    description: ClassVar[str]
    expected: ClassVar[str]
    """The node's required reaction, in words (the catalogue in docs/safety.md)."""
    ends_episode: ClassVar[bool] = False
    detects: ClassVar[str | None]
    answered: ClassVar[bool] = True
    needs_socketcan: ClassVar[bool] = False
    restarts_steps: ClassVar[bool] = False
    """The simulator's step count starts again from 0 (a restarted sender)."""

    @abstractmethod
    def apply(self, ctx: Context, frames: list[can.Message], obs: np.ndarray, step: int) -> dict[str, Any]:
        """Inject the fault in place of sending ``frames`` (the observation ``obs`` of ``step``)."""


class Loss(Injector):
    name = "loss"
    description = "the second observation frame of the step is lost"
    expected = "no action from a partial observation; the resent step is answered (counter jump counted)"
    detects = "sequence_errors"

    def apply(self, ctx: Context, frames: list[can.Message], obs: np.ndarray, step: int) -> dict[str, Any]:
        ctx.link.send([f for k, f in enumerate(frames) if k != 1])
        return {}


class Burst(Injector):
    name = "burst"
    description = f"{BURST_FRAMES} frames of every observation message lost"
    expected = "frames beyond the counter window dropped; the sequence re-synchronises on the next one"
    detects = "resyncs"

    def apply(self, ctx: Context, frames: list[can.Message], obs: np.ndarray, step: int) -> dict[str, Any]:
        ctx.codec.skip_counters(BURST_FRAMES)
        fresh, _ = ctx.codec.encode_observation(obs, step)
        ctx.link.send(fresh)
        return {}


class Duplicate(Injector):
    name = "duplicate"
    description = "every frame of the step sent twice"
    expected = "the copies dropped as repeated counters; exactly one action for the step"
    detects = "sequence_errors"

    def apply(self, ctx: Context, frames: list[can.Message], obs: np.ndarray, step: int) -> dict[str, Any]:
        ctx.link.send([copy for f in frames for copy in (f, _copy(f))])
        return {}


class Replay(Injector):
    name = "replay"
    description = "the previous step's frames sent again verbatim, then this step"
    expected = "the replayed frames dropped (old counters); this step answered"
    detects = "sequence_errors"

    def apply(self, ctx: Context, frames: list[can.Message], obs: np.ndarray, step: int) -> dict[str, Any]:
        ctx.link.send([_copy(f) for f in ctx.previous or []])
        ctx.link.send(frames)
        return {"replayed_frames": len(ctx.previous or [])}


class ReplayFresh(Injector):
    name = "replay-fresh"
    description = "the previous step re-sent with valid counters and CRCs (a forged replay), then this step"
    expected = "the old step completes but is not answered (its Step does not go forward); this step answered"
    detects = "stale_steps"

    def apply(self, ctx: Context, frames: list[can.Message], obs: np.ndarray, step: int) -> dict[str, Any]:
        if ctx.previous is None:
            raise ValueError("replay-fresh needs a previous step: schedule it at step 1 or later")
        ctx.codec.rewind()  # this step's frames go after the replay, with the counters after its
        old = [_copy(f) for f in ctx.previous]
        for frame in old:  # fresh counters, recomputed CRC: only the Step shows it is old
            message = ctx.codec.db.get_message_by_frame_id(frame.arbitration_id)
            fields = cast(
                dict[str, Any], message.decode(bytes(frame.data), decode_choices=False, scaling=False)
            )
            fields["Counter"] = ctx.codec.next_counter(message.name)
            frame.data = bytearray(e2e.protect(frame.arbitration_id, message.encode(fields, scaling=False)))
        fresh, _ = ctx.codec.encode_observation(obs, step)
        ctx.link.send(old)
        ctx.link.send(fresh)
        return {}


class Reorder(Injector):
    name = "reorder"
    description = "the step's frames sent in reverse order"
    expected = "tolerated: the same action as in order"
    detects = None

    def apply(self, ctx: Context, frames: list[can.Message], obs: np.ndarray, step: int) -> dict[str, Any]:
        ctx.link.send(list(reversed(frames)))
        return {}


class Delay(Injector):
    name = "delay"
    description = f"the step's frames held for {DELAY_FACTOR} watchdog timeouts (on the node's clock)"
    expected = "SAFE at the timeout with the safe action; the late step answered with the safe action"
    detects = "timeouts"

    def apply(self, ctx: Context, frames: list[can.Message], obs: np.ndarray, step: int) -> dict[str, Any]:
        timeout_s = ctx.node_timeout_ms / 1000
        if ctx.node.simulated_time:  # exactly the hold, in the node's (the simulation's) time
            pass_time(ctx, DELAY_FACTOR * timeout_s)
            ctx.link.send(frames)
            return {"held_ms": round(DELAY_FACTOR * timeout_s * 1000, 1), "clock": "simulated"}
        start = time.monotonic()
        before = ctx.link.stats.last_status
        ctx.link.drain(DELAY_FACTOR * timeout_s)
        give_up = start + DELAY_MAX_FACTOR * timeout_s
        while not _timed_out_since(before, ctx.link.stats.last_status) and time.monotonic() < give_up:
            ctx.link.drain(DELAY_POLL_FACTOR * timeout_s)
        ctx.link.send(frames)
        return {"held_ms": round((time.monotonic() - start) * 1000, 1), "clock": "real"}


def pass_time(ctx: Context, seconds: float, until: Callable[[Any], bool] | None = None) -> float | None:
    """For a node on the simulation's clock: let ``seconds`` of that time pass, a NodeStatus period
    (:data:`TIME_STEP_S`) at a time, reading what the node sends after each; with ``until``, stop at the
    first decoded frame it accepts and return the simulated seconds passed by then (None: never)."""
    passed = 0.0
    while passed < seconds:
        part = min(TIME_STEP_S, seconds - passed)
        ctx.node.advance(part)
        passed += part
        while (decoded := ctx.link.receive(SETTLE_S)) is not False:
            if until is not None and until(decoded):
                return passed
    return None


def _timed_out_since(before: Status | None, now: Status | None) -> bool:
    """Whether the node's status reports a watchdog timeout after ``before`` (None: no status yet)."""
    if now is None:
        return False
    return now.timeouts > (before.timeouts if before is not None else 0)


class Corrupt(Injector):
    name = "corrupt"
    description = "one payload bit of the second observation frame flipped"
    expected = "the frame dropped (CRC); the resent step answered"
    detects = "crc_errors"

    def apply(self, ctx: Context, frames: list[can.Message], obs: np.ndarray, step: int) -> dict[str, Any]:
        bad = bytearray(frames[1].data)
        bad[4] ^= 0x10
        frames[1].data = bad
        ctx.link.send(frames)
        return {}


class Masquerade(Injector):
    name = "masquerade"
    description = "the first frame's payload sent under the second frame's ID (wrong data ID)"
    expected = "the frame dropped (the CRC covers the data ID); the resent step answered"
    detects = "crc_errors"

    def apply(self, ctx: Context, frames: list[can.Message], obs: np.ndarray, step: int) -> dict[str, Any]:
        fake = _copy(frames[0])
        fake.arbitration_id = frames[1].arbitration_id
        ctx.link.send([frames[0], fake, *frames[2:]])
        return {}


class OutOfRange(Injector):
    name = "out-of-range"
    description = "the first observation field sent beyond its range in the DBC"
    expected = "the frame dropped and counted, never given to the policy; the resent step answered"
    detects = "range_errors"

    def apply(self, ctx: Context, frames: list[can.Message], obs: np.ndarray, step: int) -> dict[str, Any]:
        slot = layout(ctx.interface).observation_slots[0]
        wrong = np.array(obs, dtype=np.float32)
        wrong[slot.index] = slot.field.high + 64 * slot.scale
        ctx.codec.rewind()
        bad, _ = ctx.codec.encode_observation(wrong, step)  # the other fields as they were
        ctx.link.send(bad)
        return {"value": float(wrong[slot.index]), "high": slot.field.high}


class Flood(Injector):
    name = "flood"
    description = (
        f"frames of foreign ID 0x{FLOOD_ID:03X}, as fast as the bus takes them, until the episode ends"
    )
    expected = (
        "tolerated: every step answered as in the simulation; the node's bus filter keeps the flood out"
    )
    detects = None

    def apply(self, ctx: Context, frames: list[can.Message], obs: np.ndarray, step: int) -> dict[str, Any]:
        start = time.monotonic()
        finish = _flood_socketcan(ctx.iface) if ctx.bus_kind == "socketcan" else _flood_python(ctx)

        def done() -> dict[str, Any]:
            sent = finish()
            seconds = time.monotonic() - start
            return {"flood_frames": sent, "flood_s": seconds, "flood_frames_per_s": sent / seconds}

        ctx.at_episode_end.append(done)
        time.sleep(ctx.node_timeout_ms / 4000)  # the flood is on when the step goes out (the node waits)
        ctx.link.send(frames)
        return {}


def _flood_socketcan(iface: str) -> Callable[[], int]:
    """can-utils' ``cangen`` with no gap (C, one write per frame, waiting only when the queue is full)."""
    cangen = shutil.which("cangen")
    if cangen is None:
        raise FileNotFoundError("the flood needs cangen from can-utils (make deps installs it)")
    process = subprocess.Popen(
        [cangen, iface, "-g", "0", "-p", "10", "-I", f"{FLOOD_ID:03X}", "-L", "8", "-D", "i", "-x"],
        stdout=subprocess.DEVNULL,
        stderr=subprocess.DEVNULL,
    )
    counter = can_statistics(iface)

    def stop() -> int:
        process.terminate()
        process.wait()
        return can_statistics(iface) - counter

    return stop


def _flood_python(ctx: Context) -> Callable[[], int]:
    """python-can's virtual bus has no kernel filter: the flood is paced (:data:`VIRTUAL_FLOOD_GAP_S`)."""
    import can

    sent = [0]
    halt = threading.Event()

    def flood() -> None:
        with can.Bus(interface=ctx.bus_kind, channel=ctx.iface, receive_own_messages=False) as bus:
            junk = can.Message(arbitration_id=FLOOD_ID, data=bytes(8), is_extended_id=False)
            end = time.monotonic() + FLOOD_MAX_S
            while not halt.is_set() and time.monotonic() < end:
                bus.send(junk)
                sent[0] += 1
                time.sleep(VIRTUAL_FLOOD_GAP_S)

    thread = threading.Thread(target=flood, name="flood", daemon=True)
    thread.start()

    def stop() -> int:
        halt.set()
        thread.join()
        return sent[0]

    return stop


def can_statistics(iface: str) -> int:
    """Frames the interface has carried so far (the kernel's tx_packets: the flood and the session)."""
    return int(Path(f"/sys/class/net/{iface}/statistics/tx_packets").read_text())


class BusOff(Injector):
    name = "bus-off"
    description = "error frames: the controller error passive, then bus-off; restarted at the episode's end"
    expected = "the bus state in NodeDiag follows (PASSIVE, BUS_OFF, ACTIVE after the restart)"
    detects = "bus_state"
    needs_socketcan = True

    def apply(self, ctx: Context, frames: list[can.Message], obs: np.ndarray, step: int) -> dict[str, Any]:
        import can

        def error_frame(bits: int, data: bytes = bytes(8)) -> can.Message:
            return can.Message(arbitration_id=bits, data=data, is_error_frame=True, is_extended_id=False)

        with can.Bus(interface=ctx.bus_kind, channel=ctx.iface, receive_own_messages=False) as bus:
            bus.send(error_frame(CAN_ERR_CRTL, bytes([0, CAN_ERR_CRTL_RX_PASSIVE, 0, 0, 0, 0, 0, 0])))
            passive = ctx.link.snapshot(1.0)
            bus.send(error_frame(CAN_ERR_BUSOFF))

        def restart() -> dict[str, Any]:
            with can.Bus(interface=ctx.bus_kind, channel=ctx.iface, receive_own_messages=False) as bus:
                bus.send(error_frame(CAN_ERR_RESTARTED))
            after = ctx.link.snapshot(1.0)
            return {"bus_state_after_restart": after[1].bus_state if after else None}

        ctx.at_episode_end.append(restart)
        ctx.link.send(frames)
        return {"bus_state_when_passive": passive[1].bus_state if passive else None}


class Silence(Injector):
    name = "silent"
    description = "the simulator stops sending"
    expected = "SAFE within the watchdog timeout, the interface's safe action sent"
    detects = "timeouts"
    ends_episode = True
    answered = False

    def apply(self, ctx: Context, frames: list[can.Message], obs: np.ndarray, step: int) -> dict[str, Any]:
        clock, listen = ("simulated", _safe_in_simulated_time) if ctx.node.simulated_time else ("real", _safe)
        safe_after_s, safe_seen = listen(ctx)
        return {
            "safe_action_after_ms": None if safe_after_s is None else round(safe_after_s * 1000, 3),
            "safe_action": safe_seen,
            "expected_safe_action": list(ctx.interface.safe_action),
            "node_timeout_ms": ctx.node_timeout_ms,
            "clock": clock,
        }


def _safe(ctx: Context) -> tuple[float | None, list[float] | None]:
    """The node's first safe action within :data:`SILENCE_S` of real time: how long after the silence
    began (seconds: to the frame's arrival at the socket, so that a busy machine's delay in waking this
    process does not count against the node) and its values; (None, None) if none came."""
    from embedrl.hil.codec import Action

    began, last_sent = time.time(), time.monotonic()
    deadline = last_sent + SILENCE_S
    while (remaining := deadline - time.monotonic()) > 0:
        decoded = ctx.link.receive(remaining)
        if decoded is False:
            break
        if isinstance(decoded, Action) and is_safe(decoded.action, ctx.interface):
            return max(ctx.link.received_at - began, 0.0), decoded.action.tolist()
    return None, None


def _safe_in_simulated_time(ctx: Context) -> tuple[float | None, list[float] | None]:
    """:func:`_safe` for a node on the simulation's clock: the simulation's time goes on without a frame
    (:func:`pass_time`, at least two watchdog timeouts), measured from the last observation the node got
    (the silent step's sample time has passed already)."""
    from embedrl.hil.codec import Action

    seen: list[list[float]] = []

    def safe(decoded: Any) -> bool:
        if isinstance(decoded, Action) and is_safe(decoded.action, ctx.interface):
            seen.append(decoded.action.tolist())
        return bool(seen)

    after = pass_time(ctx, max(SILENCE_S, 2 * ctx.node_timeout_ms / 1000), safe)
    return (None, None) if after is None else (after + ctx.interface.sample_time_s, seen[0])


class LinkDownUp(Injector):
    name = "link-down-up"
    description = f"the CAN interface set down for {LINK_DOWN_S} s, then up"
    expected = "the node stays up, SAFE while down; it re-opens the interface and answers (safe action first)"
    detects = "link_resets"
    needs_socketcan = True

    def apply(self, ctx: Context, frames: list[can.Message], obs: np.ndarray, step: int) -> dict[str, Any]:
        _ip("link", "set", ctx.iface, "down")
        time.sleep(LINK_DOWN_S)
        _ip("link", "set", ctx.iface, "up")
        ctx.link.drain(0.3)  # the node re-opens every 100 ms
        ctx.link.send(frames)
        return {"node_alive": ctx.node.alive()}


class KillRestart(Injector):
    name = "kill-restart"
    description = "the node killed (SIGKILL) and started again"
    expected = "the death seen by the simulator; the restarted node answers the step"
    detects = "node_exit"

    def apply(self, ctx: Context, frames: list[can.Message], obs: np.ndarray, step: int) -> dict[str, Any]:
        ctx.node.kill()
        died = not ctx.node.alive()
        reason = ctx.node.exit_reason()
        ctx.node.restart()
        ctx.codec.receivers.clear()  # the simulator restarted it: its counters start from 0 again
        ctx.link.snapshot(1.0)  # the fresh node is up once it reports
        ctx.link.send(frames)
        return {"node_died": died, "node_exit": reason}


class SenderRestart(Injector):
    name = "sender-restart"
    description = "the simulator restarts: its counters and its step count start from 0 again"
    expected = "the node re-synchronises (or times out to SAFE) and answers the new steps"
    detects = "resyncs|stale_steps|timeouts"
    restarts_steps = True

    def apply(self, ctx: Context, frames: list[can.Message], obs: np.ndarray, step: int) -> dict[str, Any]:
        ctx.codec.restart()
        fresh, _ = ctx.codec.encode_observation(obs, 0)  # the session counts its steps from 0 again
        ctx.link.send(fresh)
        return {}


class Kill(Injector):
    name = "kill"
    description = "the node dies (SIGKILL) and stays dead"
    expected = "the step unanswered: the episode ends as a fault naming the node's exit, not a hang"
    detects = "node_exit"
    answered = False

    def apply(self, ctx: Context, frames: list[can.Message], obs: np.ndarray, step: int) -> dict[str, Any]:
        ctx.node.kill()
        return {"node_exit": ctx.node.exit_reason()}


CATALOGUE: tuple[Injector, ...] = (
    Loss(), Burst(), Duplicate(), Replay(), ReplayFresh(), Reorder(), Delay(), Corrupt(), Masquerade(),
    OutOfRange(), Flood(), LinkDownUp(), BusOff(), KillRestart(), SenderRestart(), Silence(), Kill(),
)  # fmt: skip
INJECTORS: dict[str, Injector] = {i.name: i for i in CATALOGUE}


@dataclass(frozen=True)
class Scheduled:
    injector: Injector
    episode: int
    step: int


def parse_schedule(entries: list[str]) -> list[Scheduled]:
    """``NAME`` or ``NAME@EPISODE:STEP`` (step within the episode), each at most once per step."""
    schedule = []
    for entry in entries:
        name, _, when = entry.partition("@")
        if name not in INJECTORS:
            raise ValueError(f"unknown fault {name!r}; the catalogue: {', '.join(INJECTORS)}")
        episode, step = 0, INJECT_STEP
        if when:
            try:
                episode_text, step_text = when.split(":")
                episode, step = int(episode_text), int(step_text)
            except ValueError:
                raise ValueError(f"--inject {entry!r}: expected NAME@EPISODE:STEP, e.g. {name}@0:3") from None
            if episode < 0 or step < 1:
                raise ValueError(f"--inject {entry!r}: the episode must be >= 0 and the step >= 1")
        schedule.append(Scheduled(INJECTORS[name], episode, step))
    slots = [(s.episode, s.step) for s in schedule]
    if len(set(slots)) != len(slots):
        raise ValueError("--inject: two faults scheduled at the same step")
    return schedule


def is_safe(action: np.ndarray, interface: Interface) -> bool:
    """Whether ``action`` is the interface's safe action, within the CAN quantisation."""
    step = max(slot.scale for slot in layout(interface).action_slots)
    return bool(np.max(np.abs(action - np.asarray(interface.safe_action))) <= step)


def _copy(frame: can.Message) -> can.Message:
    import can

    return can.Message(arbitration_id=frame.arbitration_id, data=bytes(frame.data), is_extended_id=False)


def _ip(*argv: str) -> None:
    subprocess.run([system_tool("ip") or "ip", *argv], check=True, capture_output=True, timeout=10)
