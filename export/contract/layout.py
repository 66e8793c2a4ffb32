"""The CAN frames of a policy node: which field travels in which frame, at which bits and scale.

Classic CAN, 8-byte frames, every frame E2E protected (:mod:`.e2e`):

- ``ObservationA, B, ...`` (IDs from 0x100, simulator -> node): ``Crc`` (8 bits), ``Counter`` (4),
  ``Step`` (12, the same in every frame of one step), then two observation fields of 20 bits each, in
  the interface's order;
- ``Action`` (0x200; ``ActionA, B, ...`` from 0x200 if there are more than two actions, node ->
  simulator): the same header, ``Step`` echoing the observation it answers, two action fields per frame;
- ``EpisodeStart`` (observation ID + 0x1F, simulator -> node; only for a policy with memory, whose interface
  has a ``state_size``): ``Crc``, ``Counter`` and the ``Step`` the new episode starts at; the node resets
  the policy's state to zero (as it does at start-up and whenever it enters SAFE);
- ``NodeStatus`` (0x300, node -> simulator, every :data:`STATUS_PERIOD_MS`, the DBC's cycle time): RUN,
  SAFE or START (running, the policy at zero state before its first step) and the node's error counters;
- ``NodeDiag`` (0x301, node -> simulator, same cycle): the CAN controller's bus state and the counters of
  the node's recovery rules (:data:`DIAG_COUNTERS`).

Each field is a signed 20-bit signal with a power-of-two scale: the finest, :data:`FINEST_SCALE`,
unless the field's range needs a coarser one. With ``fd`` the observation and action frames are CAN FD
frames of 64 bytes, 24 values each (status and diagnosis stay classic).
"""

from __future__ import annotations

import math
import string
from dataclasses import dataclass

from embedrl.export.contract.errors import ContractError
from embedrl.train.interface import Field, Interface

OBSERVATION_FIRST_ID = 0x100
ACTION_FIRST_ID = 0x200
STATUS_ID = 0x300
DIAG_ID = 0x301
MAX_NODES = 8
"""Nodes on one bus: node ``k``'s observation and action IDs are node 0's plus ``k`` * :data:`NODE_STRIDE`,
its NodeStatus and NodeDiag ``0x300 + 2k`` and ``0x301 + 2k``. Node 0's are the IDs above."""
NODE_STRIDE = 0x20
EPISODE_START_OFFSET = 0x1F
"""EpisodeStart's ID after the node's first observation ID (beyond the most observation frames)."""
FRAME_BYTES = 8
FD_FRAME_BYTES = 64
"""``fd=True``: observations and actions in CAN FD frames of 64 bytes, 24 values each (status: classic)."""
VALUE_BITS = 20
HEADER_BITS = 24
"""Crc, Counter and Step before the values."""
VALUES_PER_FRAME = 2
FINEST_SCALE = 2.0**-18
"""Quantisation step of every field unless its range needs a coarser one: the rounding error is at most
half of it, 1.9e-6, five times below the export's verification tolerance of 1e-5."""
STEP_MODULO = 4096
"""``Step`` is 12 bits: the simulation step modulo 4096."""
STATUS_PERIOD_MS = 100
"""The node sends NodeStatus this often (the DBC's cycle time of NodeStatus)."""
WATCHDOG_MS = 500
"""The node's default watchdog: no valid observation for this long -> SAFE. Longer than the control
period of every scenario, so a real-time loop never trips it."""
MAX_FRAMES = len(string.ascii_uppercase)
STATUS_STATES = {0: "RUN", 1: "SAFE", 2: "START"}
"""NodeStatus's State: START is RUN with the policy at zero state, no observation answered since start-up or
a reset (a restarted node says so until its first step)."""
BUS_STATES = {0: "ACTIVE", 1: "PASSIVE", 2: "BUS_OFF"}
DIAG_COUNTERS = (
    ("Resyncs", 6, "Alive-counter re-synchronisations (a loss burst or a sender restart)"),
    ("RangeErrors", 8, "Observation frames dropped for a signal outside its range"),
    ("StaleSteps", 8, "Observations dropped because their Step was not after the last answered one"),
    ("Incomplete", 8, "Observation steps abandoned before all their frames arrived"),
    (
        "ActionFaults",
        8,
        "Policy outputs refused (non-finite, outside the action's range, or an error status): the safe "
        "action was sent and the node went SAFE",
    ),
    ("SendFailures", 8, "Frames the CAN interface refused to send"),
    ("LinkResets", 4, "Times the CAN interface failed and was re-opened"),
)
"""NodeDiag's counters after its header (Crc, Counter, BusState): name, bits (saturating), meaning."""


@dataclass(frozen=True)
class Slot:
    """Where one field travels: its message, signal name and scale."""

    index: int
    field: Field
    message: str
    signal: str
    scale: float


@dataclass(frozen=True)
class Layout:
    """The messages of one interface, in frame order."""

    observation: tuple[tuple[str, int, tuple[Slot, ...]], ...]
    """(message name, frame ID, slots) per observation frame."""
    action: tuple[tuple[str, int, tuple[Slot, ...]], ...]
    fd: bool = False
    """CAN FD frames of :data:`FD_FRAME_BYTES` (else classic, :data:`FRAME_BYTES`)."""

    @property
    def frame_bytes(self) -> int:
        return FD_FRAME_BYTES if self.fd else FRAME_BYTES

    @property
    def observation_slots(self) -> tuple[Slot, ...]:
        return tuple(s for _, _, slots in self.observation for s in slots)

    @property
    def action_slots(self) -> tuple[Slot, ...]:
        return tuple(s for _, _, slots in self.action for s in slots)


def scale_of(field: Field) -> float:
    """The power-of-two scale for ``field``: :data:`FINEST_SCALE`, or coarser if its range needs it.

    A signed 20-bit signal with scale ``s`` covers ``[-2**19 s, (2**19 - 1) s]``.
    """
    bound = max(abs(field.low), abs(field.high))
    exponent = math.floor(math.log2(bound)) + 1  # the smallest power of two strictly above the bound
    return float(max(FINEST_SCALE, 2.0**exponent / 2 ** (VALUE_BITS - 1)))


def rounding_errors(interface: Interface) -> dict[str, float]:
    """The largest CAN rounding error of an observation and of an action value: half their scale."""
    plan = layout(interface)
    return {
        "observation": max(s.scale for s in plan.observation_slots) / 2,
        "action": max(s.scale for s in plan.action_slots) / 2,
    }


def values_per_frame(fd: bool) -> int:
    return (8 * FD_FRAME_BYTES - HEADER_BITS) // VALUE_BITS if fd else VALUES_PER_FRAME


def _frames(
    prefix: str, first_id: int, fields: tuple[Field, ...], fd: bool
) -> tuple[tuple[str, int, tuple[Slot, ...]], ...]:
    per_frame = values_per_frame(fd)
    count = math.ceil(len(fields) / per_frame)
    if count > MAX_FRAMES:
        kind, hint = (
            ("CAN FD", "") if fd else ("classic CAN", f" (--fd carries {values_per_frame(True)} a frame)")
        )
        raise ContractError(
            f"{len(fields)} {prefix.lower()} fields need {count} {kind} frames; at most {MAX_FRAMES}{hint}"
        )
    frames = []
    for k in range(count):
        name = prefix if count == 1 and prefix == "Action" else f"{prefix}{string.ascii_uppercase[k]}"
        chunk = range(k * per_frame, min(len(fields), (k + 1) * per_frame))
        slots = tuple(Slot(i, fields[i], name, fields[i].camel, scale_of(fields[i])) for i in chunk)
        frames.append((name, first_id + k, slots))
    return tuple(frames)


def layout(interface: Interface, node_id: int = 0, fd: bool = False) -> Layout:
    """Node ``node_id``'s messages (:data:`MAX_NODES`), classic or CAN FD."""
    check_node_id(node_id)
    return Layout(
        _frames("Observation", OBSERVATION_FIRST_ID + node_id * NODE_STRIDE, interface.observation, fd),
        _frames("Action", ACTION_FIRST_ID + node_id * NODE_STRIDE, interface.action, fd),
        fd,
    )


def episode_start_id(node_id: int = 0) -> int:
    """The CAN ID of node ``node_id``'s EpisodeStart (a policy with memory only)."""
    check_node_id(node_id)
    return OBSERVATION_FIRST_ID + node_id * NODE_STRIDE + EPISODE_START_OFFSET


def status_id(node_id: int = 0) -> int:
    """NodeStatus of node ``node_id`` (its NodeDiag is the next ID)."""
    check_node_id(node_id)
    return STATUS_ID + 2 * node_id


def check_node_id(node_id: int) -> None:
    if not 0 <= node_id < MAX_NODES:
        raise ContractError(f"node ID {node_id} is outside 0..{MAX_NODES - 1}")
