"""Fault injection: a registry of injectors and when they strike.

Each injector acts once, at :data:`INJECT_STEP` of the first episode, in place of sending that step's
observation normally, and reports what it observed. ``ends_episode``: the episode ends there as a fault
(``injected: NAME``); otherwise the step goes on and the session sees what the fault did (a killed node
leaves the step unanswered).
"""

from __future__ import annotations

import time
from abc import ABC, abstractmethod
from dataclasses import dataclass
from typing import TYPE_CHECKING, Any, ClassVar

import numpy as np

from embedrl.hil import candb

if TYPE_CHECKING:  # the command lists the injectors without loading the session's machinery
    import can

    from embedrl.hil.link import Link
    from embedrl.hil.nodes import Node
    from embedrl.train.interface import Interface

INJECT_STEP = 3
"""Injections happen at this step of the first episode."""
SILENCE_S = 5.0
"""How long the silent simulator listens for the node's safe action."""


@dataclass(frozen=True)
class Context:
    link: Link
    node: Node
    interface: Interface
    node_timeout_ms: int
    action_timeout_s: float


class Injector(ABC):
    name: ClassVar[str]
    ends_episode: ClassVar[bool]

    @abstractmethod
    def apply(self, ctx: Context, frames: list[can.Message], step: int) -> dict[str, Any]:
        """Inject the fault at ``step`` (whose observation ``frames`` are ready); what was observed."""


class CorruptFrame(Injector):
    """One payload bit of the second observation frame flipped: the CRC no longer matches."""

    name, ends_episode = "corrupt", True

    def apply(self, ctx: Context, frames: list[can.Message], step: int) -> dict[str, Any]:
        before = ctx.link.wait_status(1.0)
        bad = bytearray(frames[1].data)
        bad[4] ^= 0x10
        frames[1].data = bad
        ctx.link.send(frames)
        action = ctx.link.wait_action(step, min(ctx.action_timeout_s, 3 * ctx.node_timeout_ms / 1000))
        after = ctx.link.wait_status(1.0)
        return {
            "kind": self.name,
            "action_received": action is not None,
            "node_crc_errors_before": before.crc_errors if before else None,
            "node_crc_errors_after": after.crc_errors if after else None,
        }


class SilentSimulator(Injector):
    """The simulator stops sending: the node's watchdog must send the interface's safe action."""

    name, ends_episode = "silent", True

    def apply(self, ctx: Context, frames: list[can.Message], step: int) -> dict[str, Any]:
        from embedrl.hil.codec import Action

        last_sent = time.monotonic()
        deadline = last_sent + SILENCE_S
        safe_after_ms, safe_seen = None, None
        while (remaining := deadline - time.monotonic()) > 0:
            decoded = ctx.link.receive(remaining)
            if decoded is False:
                break
            if isinstance(decoded, Action) and is_safe(decoded.action, ctx.interface):
                safe_after_ms = (time.monotonic() - last_sent) * 1000
                safe_seen = decoded.action.tolist()
                break
        status = ctx.link.wait_status(1.0)
        return {
            "kind": self.name,
            "safe_action_after_ms": safe_after_ms,
            "safe_action": safe_seen,
            "expected_safe_action": list(ctx.interface.safe_action),
            "node_timeout_ms": ctx.node_timeout_ms,
            "node_state": status.state if status else None,
        }


class KillNode(Injector):
    """The node dies (SIGKILL for the C node): the step goes unanswered and must end as a fault."""

    name, ends_episode = "kill", False

    def apply(self, ctx: Context, frames: list[can.Message], step: int) -> dict[str, Any]:
        ctx.node.kill()
        return {"kind": self.name, "node_exit": ctx.node.exit_reason()}


INJECTORS: dict[str, Injector] = {i.name: i for i in (CorruptFrame(), SilentSimulator(), KillNode())}


def is_safe(action: np.ndarray, interface: Interface) -> bool:
    """Whether ``action`` is the interface's safe action, within the CAN quantisation."""
    step = max(slot.scale for slot in candb.layout(interface).action_slots)
    return bool(np.max(np.abs(action - np.asarray(interface.safe_action))) <= step)
