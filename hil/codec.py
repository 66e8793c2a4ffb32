"""Encode observations and decode actions and status with cantools, from hil/policy.dbc."""

from __future__ import annotations

from dataclasses import dataclass, field
from pathlib import Path
from typing import Any, cast

import can
import cantools
import numpy as np

from hil import e2e

DBC_PATH = Path(__file__).with_name("policy.dbc")
OBSERVATION_MESSAGES = ("ObservationA", "ObservationB", "ObservationC")
OBSERVATION_SIGNALS = (("X", "Y"), ("SinTheta", "CosTheta"), ("Speed", "TurnRate"))
"""Signals of each observation frame, in the observation's order (x, y, sin, cos, v, w)."""
STEP_MODULO = 4096


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


def load_database() -> cantools.database.can.Database:
    db = cantools.database.load_file(str(DBC_PATH))
    assert isinstance(db, cantools.database.can.Database)
    return db


def decode_fields(message: cantools.database.can.Message, data: bytes) -> dict[str, Any]:
    """Signal values of an 8-byte frame (raw choices as numbers)."""
    return cast(dict[str, Any], message.decode(data, decode_choices=False))


@dataclass
class Codec:
    """Both directions of the simulator's side; E2E counters and checks included."""

    db: cantools.database.can.Database = field(default_factory=load_database)
    counters: dict[str, int] = field(default_factory=dict)
    receivers: dict[int, e2e.Receiver] = field(default_factory=dict)
    crc_errors: int = 0
    sequence_errors: int = 0

    def __post_init__(self) -> None:
        self.action_id = self.db.get_message_by_name("Action").frame_id
        self.status_id = self.db.get_message_by_name("NodeStatus").frame_id

    def _next_counter(self, name: str) -> int:
        value = self.counters.get(name, 0)
        self.counters[name] = (value + 1) % e2e.COUNTER_MODULO
        return value

    def encode_observation(self, obs: np.ndarray, step: int) -> tuple[list[can.Message], np.ndarray]:
        """The three frames of one observation and the observation the node will decode from them."""
        frames, decoded = [], []
        for name, signals, values in zip(
            OBSERVATION_MESSAGES, OBSERVATION_SIGNALS, np.reshape(obs, (3, 2)), strict=True
        ):
            message = self.db.get_message_by_name(name)
            counter = self._next_counter(name)
            payload: dict[str, float] = {"Crc": 0, "Counter": counter, "Step": step % STEP_MODULO}
            payload.update({s: float(v) for s, v in zip(signals, values, strict=True)})
            data = e2e.protect(message.frame_id, message.encode(payload, scaling=True, strict=False))
            frames.append(can.Message(arbitration_id=message.frame_id, data=data, is_extended_id=False))
            back = decode_fields(message, data)
            decoded += [back[s] for s in signals]
        return frames, np.array(decoded, dtype=np.float32)

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

    def decode(self, msg: can.Message) -> Action | Status | None:
        """An E2E-valid Action or NodeStatus, or None (other IDs, bad CRC, repeated or old counter)."""
        if msg.is_extended_id or msg.arbitration_id not in (self.action_id, self.status_id) or msg.dlc != 8:
            return None
        fields = self._checked(msg)
        if fields is None:
            return None
        if msg.arbitration_id == self.action_id:
            action = np.array([fields["ForceLeft"], fields["ForceRight"]], dtype=np.float32)
            return Action(int(fields["Step"]), action)
        return Status(
            "SAFE" if int(fields["State"]) == 1 else "RUN",
            int(fields["FramesOk"]),
            int(fields["CrcErrors"]),
            int(fields["SequenceErrors"]),
            int(fields["Timeouts"]),
            int(fields["InferenceUs"]),
        )
