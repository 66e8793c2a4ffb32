"""The CAN database of a policy node, generated from the policy's interface with cantools' database API.

Layout (classic CAN, 8-byte frames, every frame E2E protected, see :mod:`hil.e2e`):

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
  the node's recovery rules (range errors, stale steps, counter resynchronisations, incomplete steps,
  saturated actions, failed sends, link re-opens).

Each field is a signed 20-bit signal with a power-of-two scale: the finest, :data:`FINEST_SCALE`,
unless the field's range needs a coarser one. The DBC's minimum and maximum are the field's range, so
cantools' generated ``*_is_in_range`` checks it at the node's trust boundary. Besides the DBC, this
module generates the node's C: cantools' codec (``policy_dbc.c/h``) and the glue that maps frames to the
policy's observation and action vectors (``policy_io.c/h``), both never edited by hand.

Run as ``python -m embedrl.hil.candb (--scenario NAME | --interface FILE) --out DIR [--dbc-only]
[--use-float] [--nodes N] [--fd]``.
"""

from __future__ import annotations

import argparse
import math
import string
import sys
from collections import OrderedDict
from dataclasses import dataclass
from pathlib import Path

from cantools.database.can import Database, Message, Node, Signal
from cantools.database.can.c_source import camel_to_snake_case
from cantools.database.can.c_source import generate as generate_c
from cantools.database.can.formats.dbc.dbc_attribute import DbcAttribute
from cantools.database.can.formats.dbc.dbc_attribute_definition import DbcAttributeDefinition
from cantools.database.can.formats.dbc.dbc_specifics import DbcSpecifics
from cantools.database.conversion import BaseConversion

from embedrl.common import read_json
from embedrl.export.ops.base import c_float
from embedrl.hil import e2e
from embedrl.hil.errors import HilError
from embedrl.train.interface import Field, Interface, InterfaceError
from embedrl.train.scenarios import SCENARIOS

OBSERVATION_FIRST_ID = 0x100
ACTION_FIRST_ID = 0x200
STATUS_ID = 0x300
DIAG_ID = 0x301
MAX_NODES = 8
EPISODE_START_OFFSET = 0x1F
"""EpisodeStart's ID after the node's first observation ID (beyond the most observation frames)."""
"""Nodes on one bus: node ``k``'s observation and action IDs are node 0's plus ``k`` * :data:`NODE_STRIDE`,
its NodeStatus and NodeDiag ``0x300 + 2k`` and ``0x301 + 2k``. Node 0's are the IDs above."""
NODE_STRIDE = 0x20
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
DATABASE_NAME = "policy_dbc"
SIMULATOR, NODE = "SIM", "NODE"
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
CRC_COMMENT = "CRC-8 SAE J1850 over the data ID (the CAN ID, low byte then high byte) and bytes 1..7"
COUNTER_COMMENT = "4-bit alive counter of this message"


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
        raise HilError(
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
    _check_node_id(node_id)
    return Layout(
        _frames("Observation", OBSERVATION_FIRST_ID + node_id * NODE_STRIDE, interface.observation, fd),
        _frames("Action", ACTION_FIRST_ID + node_id * NODE_STRIDE, interface.action, fd),
        fd,
    )


def episode_start_id(node_id: int = 0) -> int:
    """The CAN ID of node ``node_id``'s EpisodeStart (a policy with memory only)."""
    _check_node_id(node_id)
    return OBSERVATION_FIRST_ID + node_id * NODE_STRIDE + EPISODE_START_OFFSET


def status_id(node_id: int = 0) -> int:
    """NodeStatus of node ``node_id`` (its NodeDiag is the next ID)."""
    _check_node_id(node_id)
    return STATUS_ID + 2 * node_id


def _check_node_id(node_id: int) -> None:
    if not 0 <= node_id < MAX_NODES:
        raise HilError(f"node ID {node_id} is outside 0..{MAX_NODES - 1}")


def _header(receiver: str, step_comment: str) -> list[Signal]:
    return [
        Signal("Crc", 0, 8, receivers=[receiver], minimum=0, maximum=255, comment=CRC_COMMENT),
        Signal("Counter", 8, 4, receivers=[receiver], minimum=0, maximum=15, comment=COUNTER_COMMENT),
        Signal(
            "Step", 12, 12, receivers=[receiver], minimum=0, maximum=STEP_MODULO - 1, comment=step_comment
        ),
    ]


def _value(slot: Slot, receiver: str, start: int) -> Signal:
    return Signal(
        slot.signal,
        start,
        VALUE_BITS,
        is_signed=True,
        conversion=BaseConversion.factory(scale=slot.scale, offset=0),
        minimum=_round(slot.field.low),
        maximum=_round(slot.field.high),
        unit=slot.field.unit or None,
        receivers=[receiver],
        comment=slot.field.description,
    )


def _round(value: float) -> float:
    """9 significant digits: the float32 value the env sends, written without binary noise."""
    return float(f"{value:.9g}")


def database(interface: Interface, node_id: int = 0, fd: bool = False) -> Database:
    """The cantools database of node ``node_id`` running a policy with this interface."""
    messages = node_messages(interface, node_id, fd=fd)
    nodes = [Node(SIMULATOR, None), Node(NODE, None)]
    return Database(
        messages, nodes, version=f"embedrl {interface.name}", dbc_specifics=_fd_bus() if fd else None
    )


def _fd_bus() -> DbcSpecifics:
    """The DBC attribute that marks a CAN FD bus (its messages then get VFrameFormat CAN FD)."""
    bus_type = DbcAttributeDefinition("BusType", default_value="CAN", type_name="STRING")
    return DbcSpecifics(
        attributes=OrderedDict(BusType=DbcAttribute("CAN FD", bus_type)),
        attribute_definitions=OrderedDict(BusType=bus_type),
    )


def node_messages(
    interface: Interface, node_id: int = 0, ecu: str = NODE, suffix: str = "", fd: bool = False
) -> list[Message]:
    """Node ``node_id``'s messages, sent and received by ``ecu``, their names ending in ``suffix``."""
    plan = layout(interface, node_id, fd)
    messages = []
    for group, sender, receiver, step_comment in (
        (
            plan.observation,
            SIMULATOR,
            NODE,
            "Simulation step (mod 4096); every observation frame of one step carries it",
        ),
        (plan.action, ecu, SIMULATOR, "Step of the observation this action answers"),
    ):
        for name, frame_id, slots in group:
            signals = _header(receiver, step_comment)
            signals += [_value(s, receiver, HEADER_BITS + VALUE_BITS * i) for i, s in enumerate(slots)]
            messages.append(
                Message(
                    frame_id,
                    name + suffix,
                    plan.frame_bytes,
                    signals,
                    senders=[sender],
                    comment=_comment(name, slots),
                    is_fd=fd,
                )
            )
    if interface.state_size:
        messages.append(_episode_start(interface, node_id, ecu, suffix))
    status = [
        Signal("Crc", 0, 8, receivers=[SIMULATOR], minimum=0, maximum=255),
        Signal("Counter", 8, 4, receivers=[SIMULATOR], minimum=0, maximum=15),
        Signal("State", 12, 2, receivers=[SIMULATOR], minimum=0, maximum=3,
               conversion=BaseConversion.factory(choices=STATUS_STATES),  # type: ignore[arg-type]
               comment="RUN; SAFE; START: running from zero policy state, no step answered since a reset"),
        Signal("FramesOk", 14, 16, receivers=[SIMULATOR], minimum=0, maximum=65535),
        Signal("CrcErrors", 30, 8, receivers=[SIMULATOR], minimum=0, maximum=255),
        Signal("SequenceErrors", 38, 8, receivers=[SIMULATOR], minimum=0, maximum=255),
        Signal("Timeouts", 46, 8, receivers=[SIMULATOR], minimum=0, maximum=255),
        Signal("InferenceUs", 54, 10, receivers=[SIMULATOR], minimum=0, maximum=1023, unit="us",
               comment="Duration of the last policy_step in microseconds (saturates)"),
    ]  # fmt: skip
    messages.append(
        Message(
            status_id(node_id),
            "NodeStatus" + suffix,
            FRAME_BYTES,
            status,
            senders=[ecu],
            cycle_time=STATUS_PERIOD_MS,
            comment="Node state and error counters (saturating), sent periodically",
        )
    )
    diag = [
        Signal("Crc", 0, 8, receivers=[SIMULATOR], minimum=0, maximum=255),
        Signal("Counter", 8, 4, receivers=[SIMULATOR], minimum=0, maximum=15),
        Signal("BusState", 12, 2, receivers=[SIMULATOR], minimum=0, maximum=3,
               conversion=BaseConversion.factory(choices=BUS_STATES),  # type: ignore[arg-type]
               comment="The CAN controller's state, from the error frames the node subscribes to"),
    ]  # fmt: skip
    start = 14
    for name, bits, comment in DIAG_COUNTERS:
        diag.append(Signal(name, start, bits, receivers=[SIMULATOR], minimum=0, maximum=2**bits - 1,
                           comment=comment))  # fmt: skip
        start += bits
    assert start == 8 * FRAME_BYTES, "NodeDiag fills its frame exactly"
    messages.append(
        Message(
            status_id(node_id) + 1,
            "NodeDiag" + suffix,
            FRAME_BYTES,
            diag,
            senders=[ecu],
            cycle_time=STATUS_PERIOD_MS,
            comment="Bus state and the recovery rules' counters (saturating), sent with NodeStatus",
        )
    )
    return messages


def _episode_start(interface: Interface, node_id: int, ecu: str, suffix: str) -> Message:
    """EpisodeStart, for a policy with memory: its state to zero before the episode's first step."""
    return Message(
        episode_start_id(node_id),
        "EpisodeStart" + suffix,
        FRAME_BYTES,
        _header(ecu, "Step of the episode's first observation"),
        senders=[SIMULATOR],
        comment=f"A new episode: the policy's {interface.state_size} floats of memory to zero",
    )


def bus_database(interface: Interface, nodes: int, fd: bool = False) -> Database:
    """The database of ``nodes`` nodes on one bus running this policy: every node's messages, their
    names suffixed with the node ID beyond node 0 (``Action_1``), nodes ``NODE``, ``NODE_1``, ..."""
    if not 1 <= nodes <= MAX_NODES:
        raise HilError(f"--nodes must be within 1..{MAX_NODES}, got {nodes}")
    messages, ecus = [], [Node(SIMULATOR, None)]
    for k in range(nodes):
        ecu, suffix = (NODE, "") if k == 0 else (f"{NODE}_{k}", f"_{k}")
        ecus.append(Node(ecu, None))
        messages += node_messages(interface, k, ecu, suffix, fd)
    return Database(
        messages, ecus, version=f"embedrl {interface.name} x{nodes}", dbc_specifics=_fd_bus() if fd else None
    )


def _comment(name: str, slots: tuple[Slot, ...]) -> str:
    return f"{name}: " + ", ".join(f"{s.field.name} (field {s.index})" for s in slots)


def dbc_text(interface: Interface, fd: bool = False) -> str:
    return str(database(interface, fd=fd).as_dbc_string())


def c_sources(interface: Interface, use_float: bool = False, fd: bool = False) -> dict[str, str]:
    """The node's generated C for this interface: cantools' codec and the frame <-> vector glue.

    ``use_float``: cantools' scaling in ``float`` instead of ``double`` (cores without double-precision
    hardware, e.g. a Cortex-M4F)."""
    db = database(interface, fd=fd)
    header, source, _, _ = generate_c(
        db, DATABASE_NAME, f"{DATABASE_NAME}.h", f"{DATABASE_NAME}.c", "unused_fuzzer.c", use_float=use_float
    )
    io_h, io_c = _glue(interface, layout(interface, fd=fd))
    return {
        f"{DATABASE_NAME}.h": header,
        f"{DATABASE_NAME}.c": source,
        "policy_io.h": io_h,
        "policy_io.c": io_c,
        e2e.PARAMS_HEADER: e2e.params_header(),
    }


def _c_name(message: str) -> str:
    """cantools' C name of a message or signal: ``ObservationA`` -> ``observation_a``."""
    return camel_to_snake_case(message)


def _glue(interface: Interface, plan: Layout) -> tuple[str, str]:
    banner = (
        f"/* Generated by embedrl (hil/candb.py) from the interface {interface.name!r} "
        f"({interface.env_id}):\n * do not edit. Maps CAN frames to the policy's observation and action "
        "vectors. */\n"
    )
    return _glue_header(banner, interface, plan), _glue_source(banner, plan)


def _glue_header(banner: str, interface: Interface, plan: Layout) -> str:
    return f"""{banner}#ifndef POLICY_IO_H
#define POLICY_IO_H

#include <stdbool.h>
#include <stdint.h>

#define POLICY_IO_OBS_DIM {len(interface.observation)}u
#define POLICY_IO_ACT_DIM {len(interface.action)}u
#define POLICY_IO_OBS_FRAMES {len(plan.observation)}u
#define POLICY_IO_OBS_FIRST_ID 0x{OBSERVATION_FIRST_ID:X}u
#define POLICY_IO_ACT_FRAMES {len(plan.action)}u
#define POLICY_IO_ACT_FIRST_ID 0x{ACTION_FIRST_ID:X}u
#define POLICY_IO_STATUS_ID 0x{STATUS_ID:X}u
#define POLICY_IO_DIAG_ID 0x{DIAG_ID:X}u
#define POLICY_IO_MAX_NODES {MAX_NODES}u
#define POLICY_IO_NODE_STRIDE 0x{NODE_STRIDE:X}u /* node k: observation and action IDs + k * stride */
#define POLICY_IO_STATUS_STRIDE 2u /* node k: NodeStatus and NodeDiag IDs + 2k */
#define POLICY_IO_EPISODE_START {int(bool(interface.state_size))}u /* 1: memory, reset by EpisodeStart */
#define POLICY_IO_EPISODE_START_OFFSET 0x{EPISODE_START_OFFSET:X}u /* its ID: first observation ID + this */
#define POLICY_IO_FRAME_BYTES {plan.frame_bytes}u
#define POLICY_IO_FD {int(plan.fd)} /* 1: observation and action frames are CAN FD */
#define POLICY_IO_STEP_MODULO {STEP_MODULO}u
#define POLICY_IO_STATUS_PERIOD_MS {STATUS_PERIOD_MS}u /* NodeStatus cycle time in the DBC */
#define POLICY_IO_WATCHDOG_MS {WATCHDOG_MS}u /* default: no valid observation this long -> SAFE */

typedef enum {{ POLICY_IO_OK = 0, POLICY_IO_OUT_OF_RANGE = 1 }} policy_io_status;

/* Decode observation frame `part` (0 .. POLICY_IO_OBS_FRAMES - 1, the frame ID minus
 * POLICY_IO_OBS_FIRST_ID) from an E2E-checked payload: its fields go to their places in obs, its Step
 * and Counter to *step and *counter. A field outside its range in the DBC gives POLICY_IO_OUT_OF_RANGE
 * and leaves obs unchanged. */
policy_io_status policy_io_decode_observation(unsigned part, const uint8_t data[POLICY_IO_FRAME_BYTES],
                                              float obs[POLICY_IO_OBS_DIM], uint16_t *step, uint8_t *counter);

/* Whether every value of act is finite and inside its field's range (the interface's action bounds,
 * widened by half the signal's resolution: a value that close is the bound after rounding, e.g. a
 * tanh that gives 1.0000002): the node sends nothing else. */
bool policy_io_action_ok(const float act[POLICY_IO_ACT_DIM]);

/* Pack action frame `part` (0 .. POLICY_IO_ACT_FRAMES - 1) with its fields of act, Step and Counter
 * (the E2E CRC byte is left for the caller). Each value is saturated to its field's range first (a value
 * outside it would wrap around in the signal's bits: 2.0 would arrive as -2.0); returns how many were. */
unsigned policy_io_encode_action(unsigned part, const float act[POLICY_IO_ACT_DIM], uint16_t step,
                                 uint8_t counter, uint8_t data[POLICY_IO_FRAME_BYTES]);

#endif /* POLICY_IO_H */
"""


def _decode_cases(plan: Layout) -> list[str]:
    """One ``case`` per observation frame: unpack, range-check every field, then store them."""
    db = DATABASE_NAME
    decode_cases = []
    for k, (name, _, slots) in enumerate(plan.observation):
        m = _c_name(name)
        checks = " ||\n            ".join(
            f"!{db}_{m}_{_c_name(s.signal)}_is_in_range(msg.{_c_name(s.signal)})" for s in slots
        )
        stores = "\n".join(
            f"        obs[{s.index}] = (float){db}_{m}_{_c_name(s.signal)}_decode(msg.{_c_name(s.signal)});"
            for s in slots
        )
        decode_cases.append(f"""    case {k}u: {{ /* {name}: {", ".join(s.field.name for s in slots)} */
        struct {db}_{m}_t msg;
        (void){db}_{m}_unpack(&msg, data, POLICY_IO_FRAME_BYTES);
        *step = msg.step;
        *counter = msg.counter;
        if ({checks}) {{
            return POLICY_IO_OUT_OF_RANGE;
        }}
{stores}
        return POLICY_IO_OK;
    }}""")
    return decode_cases


def _encode_cases(plan: Layout) -> list[str]:
    """One ``case`` per action frame: every field saturated to its range, then packed."""
    db = DATABASE_NAME
    encode_cases = []
    for k, (name, _, slots) in enumerate(plan.action):
        m = _c_name(name)
        stores = "\n".join(
            f"        msg.{_c_name(s.signal)} = {db}_{m}_{_c_name(s.signal)}_encode("
            f"(double)saturate(act[{s.index}], {c_float(s.field.low)}, {c_float(s.field.high)}, &saturated));"
            for s in slots
        )
        encode_cases.append(f"""    case {k}u: {{ /* {name}: {", ".join(s.field.name for s in slots)} */
        struct {db}_{m}_t msg;
        memset(&msg, 0, sizeof msg);
        msg.counter = counter;
        msg.step = step;
{stores}
        (void){db}_{m}_pack(data, &msg, POLICY_IO_FRAME_BYTES);
        return saturated;
    }}""")
    return encode_cases


def _glue_source(banner: str, plan: Layout) -> str:
    db = DATABASE_NAME
    decode_cases, encode_cases = _decode_cases(plan), _encode_cases(plan)
    bounds = " &&\n           ".join(
        f"is_finite(act[{s.index}]) && act[{s.index}] >= {c_float(s.field.low - s.scale / 2)} && "
        f"act[{s.index}] <= {c_float(s.field.high + s.scale / 2)}"
        for s in plan.action_slots
    )
    return f"""{banner}#include "policy_io.h"

#include <string.h>

#include "{db}.h"

policy_io_status policy_io_decode_observation(unsigned part, const uint8_t data[POLICY_IO_FRAME_BYTES],
                                              float obs[POLICY_IO_OBS_DIM], uint16_t *step, uint8_t *counter)
{{
    switch (part) {{
{chr(10).join(decode_cases)}
    default:
        return POLICY_IO_OUT_OF_RANGE;
    }}
}}

/* v within [lo, hi]; anything else (NaN included) is moved to the nearest bound and counted. */
static float saturate(float v, float lo, float hi, unsigned *count)
{{
    if (v >= lo && v <= hi) {{
        return v;
    }}
    *count += 1u;
    return v > hi ? hi : lo;
}}

/* A bit test of the exponent: it holds under -ffast-math, where comparisons may assume no NaN. */
static bool is_finite(float v)
{{
    uint32_t bits;
    memcpy(&bits, &v, sizeof bits);
    return (bits & 0x7F800000u) != 0x7F800000u;
}}

bool policy_io_action_ok(const float act[POLICY_IO_ACT_DIM])
{{
    return {bounds};
}}

unsigned policy_io_encode_action(unsigned part, const float act[POLICY_IO_ACT_DIM], uint16_t step,
                                 uint8_t counter, uint8_t data[POLICY_IO_FRAME_BYTES])
{{
    unsigned saturated = 0u;
    memset(data, 0, POLICY_IO_FRAME_BYTES);
    switch (part) {{
{chr(10).join(encode_cases)}
    default:
        return saturated;
    }}
}}
"""


def load_interface(path: Path) -> Interface:
    """An export's ``interface.json`` (untrusted input: validated)."""
    try:
        return Interface.from_json(read_json(path))
    except (OSError, ValueError) as exc:
        raise HilError(f"{path}: {exc}") from None


def write(
    interface: Interface,
    out: Path,
    dbc_only: bool = False,
    use_float: bool = False,
    nodes: int = 1,
    fd: bool = False,
) -> list[Path]:
    """Write ``policy.dbc`` (``nodes`` nodes on one bus) and unless ``dbc_only`` the node's generated C
    (the same for every node: a node offsets its IDs by its ``--node-id`` at run time) into ``out``. A file
    whose text is unchanged is left alone, so make rebuilds nothing when nothing changed."""
    out.mkdir(parents=True, exist_ok=True)
    dbc = dbc_text(interface, fd) if nodes == 1 else str(bus_database(interface, nodes, fd).as_dbc_string())
    files = {"policy.dbc": dbc} | ({} if dbc_only else c_sources(interface, use_float, fd))
    written = []
    for name, text in files.items():
        path = out / name
        if not path.is_file() or path.read_text() != text:
            path.write_text(text)
        written.append(path)
    return written


def frame_rows(interface: Interface) -> list[tuple[str, str, str, list[str]]]:
    """The CAN frames of ``interface`` (node 0) from the same database the node is built from: ID, message,
    sender and each signal as ``name (start bit, bits, scale, range, unit)``."""
    db = database(interface)
    plan = layout(interface)
    fields = {s.signal: s for _, _, slots in (*plan.observation, *plan.action) for s in slots}
    rows = []
    for message in sorted(db.messages, key=lambda m: m.frame_id):
        parts = []
        for signal in message.signals:
            slot = fields.get(signal.name)
            if slot is not None:
                unit = f" {slot.field.unit}" if slot.field.unit else ""
                parts.append(
                    f"{signal.name} ({signal.start}, {signal.length}, 2^{int(math.log2(slot.scale))}, "
                    f"[{slot.field.low:g}, {slot.field.high:g}]{unit})"
                )
            else:
                parts.append(f"{signal.name} ({signal.start}, {signal.length})")
        rows.append((f"0x{message.frame_id:03X}", message.name, ", ".join(message.senders), parts))
    return rows


def markdown_table(interface: Interface) -> str:
    """:func:`frame_rows` as a Markdown table."""
    rows = [
        "| ID | message | sent by | signals: name (start bit, bits, scale, range, unit) |",
        "|---|---|---|---|",
    ]
    rows += [
        f"| {i} | {name} | {sender} | {'; '.join(parts)} |"
        for i, name, sender, parts in frame_rows(interface)
    ]
    return "\n".join(rows) + "\n"


def main(argv: list[str] | None = None) -> int:
    parser = argparse.ArgumentParser(prog="python -m embedrl.hil.candb", description=__doc__.split("\n")[0])
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
    except (HilError, InterfaceError, OSError) as exc:
        print(f"error: {exc}", file=sys.stderr)
        return 2
    return 0


if __name__ == "__main__":
    sys.exit(main())
