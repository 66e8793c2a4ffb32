"""The cantools database of a policy node's frames (:mod:`.layout`): the DBC both sides are built from.

The DBC's minimum and maximum of a field are its range, so cantools' generated ``*_is_in_range`` checks it
at the node's trust boundary; NodeStatus and NodeDiag carry the DBC's cycle time. :func:`bus_database` is
several nodes on one bus (names suffixed with the node ID), :func:`markdown_table` the README's table.
"""

from __future__ import annotations

import math
from collections import OrderedDict

from cantools.database.can import Database, Message, Node, Signal
from cantools.database.can.formats.dbc.dbc_attribute import DbcAttribute
from cantools.database.can.formats.dbc.dbc_attribute_definition import DbcAttributeDefinition
from cantools.database.can.formats.dbc.dbc_specifics import DbcSpecifics
from cantools.database.conversion import BaseConversion

from embedrl.escape import dbc_text as safe_dbc_text
from embedrl.export.contract.errors import ContractError
from embedrl.export.contract.layout import (
    BUS_STATES,
    DIAG_COUNTERS,
    FRAME_BYTES,
    HEADER_BITS,
    MAX_NODES,
    STATUS_PERIOD_MS,
    STATUS_STATES,
    STEP_MODULO,
    VALUE_BITS,
    Slot,
    episode_start_id,
    layout,
    status_id,
)
from embedrl.export.contract.literals import dbc_number
from embedrl.train.interface import Interface

SIMULATOR, NODE = "SIM", "NODE"
CRC_COMMENT = "CRC-8 SAE J1850 over the data ID (the CAN ID, low byte then high byte) and bytes 1..7"
COUNTER_COMMENT = "4-bit alive counter of this message"


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
        minimum=dbc_number(slot.field.low),
        maximum=dbc_number(slot.field.high),
        unit=safe_dbc_text(slot.field.unit) or None,
        receivers=[receiver],
        comment=safe_dbc_text(slot.field.description),
    )


def database(interface: Interface, node_id: int = 0, fd: bool = False) -> Database:
    """The cantools database of node ``node_id`` running a policy with this interface."""
    messages = node_messages(interface, node_id, fd=fd)
    nodes = [Node(SIMULATOR, None), Node(NODE, None)]
    return Database(
        messages,
        nodes,
        version=f"embedrl {safe_dbc_text(interface.name)}",
        dbc_specifics=_fd_bus() if fd else None,
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
        raise ContractError(f"--nodes must be within 1..{MAX_NODES}, got {nodes}")
    messages, ecus = [], [Node(SIMULATOR, None)]
    for k in range(nodes):
        ecu, suffix = (NODE, "") if k == 0 else (f"{NODE}_{k}", f"_{k}")
        ecus.append(Node(ecu, None))
        messages += node_messages(interface, k, ecu, suffix, fd)
    return Database(
        messages,
        ecus,
        version=f"embedrl {safe_dbc_text(interface.name)} x{nodes}",
        dbc_specifics=_fd_bus() if fd else None,
    )


def _comment(name: str, slots: tuple[Slot, ...]) -> str:
    return f"{name}: " + ", ".join(f"{s.field.name} (field {s.index})" for s in slots)


def dbc_text(interface: Interface, fd: bool = False) -> str:
    return str(database(interface, fd=fd).as_dbc_string())


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
