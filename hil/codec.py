"""The simulator's side of the CAN contract: encode observations, decode actions and status, with E2E.

The database and the frame layout come from the policy's interface through the contract
(:mod:`embedrl.export.contract`), the same generator the node's C is built from.
"""

from __future__ import annotations

from dataclasses import dataclass
from typing import Any, cast

import can
import cantools
import numpy as np
from cantools.database.can.c_source import camel_to_snake_case

from embedrl.export.contract.dbc import database
from embedrl.export.contract.e2e import COUNTER_MODULO
from embedrl.export.contract.layout import (
    BUS_STATES,
    DIAG_COUNTERS,
    FRAME_BYTES,
    STATUS_STATES,
    STEP_MODULO,
    layout,
    status_id,
)
from embedrl.hil import e2e
from embedrl.train.interface import Interface


@dataclass(frozen=True)
class Action:
    step: int
    action: np.ndarray


@dataclass(frozen=True)
class Status:
    state: str
    frames_ok: int
    crc_errors: int
    sequence_errors: int
    timeouts: int
    inference_us: int


@dataclass(frozen=True)
class Diag:
    """NodeDiag: the bus state and the counters of the node's recovery rules."""

    bus_state: str
    resyncs: int
    range_errors: int
    stale_steps: int
    incomplete: int
    action_faults: int
    send_failures: int
    link_resets: int


def decode_fields(message: cantools.database.can.Message, data: bytes) -> dict[str, Any]:
    """Signal values of an 8-byte frame (raw choices as numbers)."""
    return cast(dict[str, Any], message.decode(data, decode_choices=False))


class Codec:
    """Both directions of the simulator's side; E2E counters and checks included."""

    def __init__(self, interface: Interface, node_id: int = 0, fd: bool = False) -> None:
        self.interface = interface
        self.db = database(interface, node_id, fd)
        self.plan = layout(interface, node_id, fd)
        self.counters: dict[str, int] = {}
        self.receivers: dict[int, e2e.Receiver] = {}
        self.crc_errors = 0
        self.sequence_errors = 0
        self.action_parts = {frame_id: slots for _, frame_id, slots in self.plan.action}
        self.status_id = status_id(node_id)
        self.diag_id = self.status_id + 1
        self.receive_ids = (*self.action_parts, self.status_id, self.diag_id)
        """Every ID the simulator listens to (its kernel filter)."""
        self._pending: dict[int, tuple[np.ndarray, set[int]]] = {}
        """Per step: the action values received so far and the frame IDs they came in."""

    def restart(self) -> None:
        """Forget the E2E counters, as a restarted simulator would (its frames start from 0 again)."""
        self.counters.clear()
        self.receivers.clear()

    def skip_counters(self, frames: int) -> None:
        """Advance every observation message's counter by ``frames``, as if that many were lost."""
        for name, _, _ in self.plan.observation:
            self.counters[name] = (self.counters.get(name, 0) + frames) % COUNTER_MODULO

    def rewind(self) -> None:
        """Take back the counters of the observation just encoded (its frames will not be sent)."""
        for name, _, _ in self.plan.observation:
            self.counters[name] = (self.counters.get(name, 0) - 1) % COUNTER_MODULO

    def next_counter(self, name: str) -> int:
        """The alive counter for the next frame of message ``name``."""
        value = self.counters.get(name, 0)
        self.counters[name] = (value + 1) % COUNTER_MODULO
        return value

    def encode_observation(self, obs: np.ndarray, step: int) -> tuple[list[can.Message], np.ndarray]:
        """The frames of one observation and the observation the node will decode from them."""
        values = np.asarray(obs, dtype=np.float32).reshape(-1)
        frames = []
        decoded = np.zeros(len(self.interface.observation), dtype=np.float32)
        for name, frame_id, slots in self.plan.observation:
            message = self.db.get_message_by_frame_id(frame_id)
            payload: dict[str, float] = {
                "Crc": 0,
                "Counter": self.next_counter(name),
                "Step": step % STEP_MODULO,
            }
            payload.update({s.signal: float(values[s.index]) for s in slots})
            data = e2e.protect(frame_id, message.encode(payload, scaling=True, strict=False))
            frames.append(
                can.Message(arbitration_id=frame_id, data=data, is_extended_id=False, is_fd=self.plan.fd)
            )
            back = decode_fields(message, data)
            for s in slots:
                decoded[s.index] = back[s.signal]
        return frames, decoded

    def encode_episode_start(self, step: int) -> list[can.Message]:
        """The EpisodeStart frame for an episode whose first observation has ``step`` (none for a policy
        without memory: its database has no such message)."""
        if not self.interface.state_size:
            return []
        message = self.db.get_message_by_name("EpisodeStart")
        payload = {"Crc": 0, "Counter": self.next_counter(message.name), "Step": step % STEP_MODULO}
        data = e2e.protect(message.frame_id, message.encode(payload, scaling=True, strict=False))
        return [can.Message(arbitration_id=message.frame_id, data=data, is_extended_id=False)]

    def _checked(self, msg: can.Message) -> dict[str, Any] | None:
        data = bytes(msg.data)
        if not e2e.crc_ok(msg.arbitration_id, data):
            self.crc_errors += 1
            return None
        message = self.db.get_message_by_frame_id(msg.arbitration_id)
        fields = decode_fields(message, data)
        receiver = self.receivers.setdefault(msg.arbitration_id, e2e.Receiver())
        verdict = receiver.check(int(fields["Counter"]))
        if verdict != "ok":
            self.sequence_errors += 1
            if verdict in ("repeated", "wrong_sequence"):
                return None
        return fields

    def decode(self, msg: can.Message) -> Action | Status | Diag | None:
        """A complete E2E-valid action (all its frames for one step), a NodeStatus or a NodeDiag, else
        None (other IDs, bad CRC, repeated or old counter, an action still missing frames)."""
        known = msg.arbitration_id in self.receive_ids
        length = self.plan.frame_bytes if msg.arbitration_id in self.action_parts else FRAME_BYTES
        if msg.is_extended_id or not known or msg.dlc != length:
            return None
        fields = self._checked(msg)
        if fields is None:
            return None
        if msg.arbitration_id == self.status_id:
            return Status(
                STATUS_STATES.get(int(fields["State"]), "UNKNOWN"),
                int(fields["FramesOk"]),
                int(fields["CrcErrors"]),
                int(fields["SequenceErrors"]),
                int(fields["Timeouts"]),
                int(fields["InferenceUs"]),
            )
        if msg.arbitration_id == self.diag_id:
            counters = {name: int(fields[name]) for name, _, _ in DIAG_COUNTERS}
            return Diag(
                BUS_STATES.get(int(fields["BusState"]), "UNKNOWN"),
                **{camel_to_snake_case(k): v for k, v in counters.items()},
            )
        step = int(fields["Step"])
        values, seen = self._pending.get(step, (np.zeros(len(self.interface.action), np.float32), set()))
        for s in self.action_parts[msg.arbitration_id]:
            values[s.index] = fields[s.signal]
        seen.add(msg.arbitration_id)
        if len(seen) < len(self.action_parts):
            self._pending = {step: (values, seen)}  # only the newest step can still complete
            return None
        self._pending.pop(step, None)
        return Action(step, values)
