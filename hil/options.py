"""What ``embedrl hil run`` is asked to do, as one frozen record (:class:`RunOptions`)."""

from __future__ import annotations

from dataclasses import dataclass, fields
from pathlib import Path
from typing import Any

from embedrl.hil.candb import WATCHDOG_MS

DEFAULT_TIMEOUT_MS = WATCHDOG_MS
"""The node's watchdog on the host (stretched by a slow guest's slowdown)."""
MAX_TIMEOUT_MS = 60_000
NODE_KINDS = ("c", "firmware", "python")


@dataclass(frozen=True)
class RunOptions:
    """What ``embedrl hil run`` is asked to do (its options, same names)."""

    export_dir: Path
    episodes: int = 10
    seed: int = 0
    realtime: bool = False
    log: Path | None = None
    """Every frame, written here (candump ``.log`` or ``.blf``)."""
    plot: Path | None = None
    """A folder for the trajectory and latency plots."""
    sandbox: str = "auto"
    timeout_ms: int | None = None
    """The node's watchdog; None: :data:`DEFAULT_TIMEOUT_MS` times the sandbox's slowdown."""
    inject: tuple[str, ...] = ()
    allow_faults: bool = False
    keep_work: bool = False
    fd: bool = False
    nodes: int = 1
    kill_node: tuple[int, int, int] | None = None
    """(node, episode, step): that node's process is killed before that step."""
    node: str = "c"
    """``c``: the compiled node over SocketCAN; ``firmware``: the Cortex-M image on QEMU, bridged over
    SLCAN; ``python``: the reference node on a virtual bus."""
    target: str = "cortex-m4"
    """The core the firmware node is built for (``node="firmware"``): a name of ``cortex_m/targets.mk``."""

    @classmethod
    def of(cls, values: dict[str, Any]) -> RunOptions:
        """The options among ``values`` (e.g. parsed command-line arguments; other keys are ignored)."""
        known = {f.name for f in fields(cls)}
        picked = {k: v for k, v in values.items() if k in known}
        picked["inject"] = tuple(picked.get("inject", ()))
        return cls(**picked)
