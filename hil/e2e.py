"""End-to-end protection, the Python side of runtime_c/node/e2e.c (AUTOSAR profile 1 style), with the
contract's parameters (:mod:`embedrl.export.contract.e2e`): the CRC of a frame and the alive-counter check.
"""

from __future__ import annotations

from dataclasses import dataclass

from embedrl.export.contract.e2e import (
    COUNTER_MODULO,
    CRC8_INIT,
    CRC8_POLY,
    CRC8_XOR_OUT,
    MAX_FORWARD_JUMP,
    RESYNC_FRAMES,
)


def crc8(data_id: int, data: bytes) -> int:
    """CRC over the data ID and bytes 1 .. len - 1 (8 bytes classic, up to 64 CAN FD)."""
    crc = CRC8_INIT
    for byte in (data_id & 0xFF, (data_id >> 8) & 0xFF, *data[1:]):
        crc ^= byte
        for _ in range(8):
            crc = ((crc << 1) ^ CRC8_POLY) & 0xFF if crc & 0x80 else (crc << 1) & 0xFF
    return crc ^ CRC8_XOR_OUT


def protect(data_id: int, data: bytes) -> bytes:
    """The frame with its CRC in byte 0."""
    return bytes([crc8(data_id, data)]) + bytes(data[1:])


def crc_ok(data_id: int, data: bytes) -> bool:
    return len(data) >= 2 and data[0] == crc8(data_id, data)


@dataclass
class Receiver:
    """Alive-counter check of one message, as the C node does it."""

    last: int | None = None
    candidate: int = 0
    candidate_run: int = 0

    def check(self, counter: int) -> str:
        """ "ok", "lost" (accepted after a forward jump), "resync" (accepted: the second consecutive
        counter of a new sequence), "repeated" or "wrong_sequence" (rejected); as ``e2e_check_counter``."""
        counter %= COUNTER_MODULO
        if self.last is None:
            self.last = counter
            return "ok"
        delta = (counter - self.last) % COUNTER_MODULO
        if delta == 0:
            return "repeated"
        if delta <= MAX_FORWARD_JUMP:
            self.last, self.candidate_run = counter, 0
            return "ok" if delta == 1 else "lost"
        follows = (self.candidate + 1) % COUNTER_MODULO
        self.candidate_run = self.candidate_run + 1 if self.candidate_run and counter == follows else 1
        self.candidate = counter
        if self.candidate_run >= RESYNC_FRAMES:
            self.last, self.candidate_run = counter, 0
            return "resync"
        return "wrong_sequence"
