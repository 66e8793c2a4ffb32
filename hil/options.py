"""What ``embedrl hil run`` is asked to do, as one frozen record (:class:`RunOptions`)."""

from __future__ import annotations

from dataclasses import dataclass, fields
from pathlib import Path
from typing import Any

from embedrl.export.contract.layout import WATCHDOG_MS
from embedrl.hil.node_kinds import DEFAULT_NODE

DEFAULT_TIMEOUT_MS = WATCHDOG_MS
"""The node's watchdog on the host (stretched by a slow guest's slowdown)."""
MIN_TIMEOUT_MS = 50
"""The shortest watchdog a run accepts. Between two observations the node waits for the simulator: its
env step and a CAN round trip, a few ms on the host and about ten times that in an emulated sandbox, and
longer at an episode's start. A shorter watchdog trips in lock-step and the run fails blaming the node."""
MAX_TIMEOUT_MS = 60_000
DEFAULT_SANDBOX = "auto"
DEFAULT_TARGET = "cortex-m4"
"""The firmware node's core unless ``--target`` names another."""
COVERAGE_TOOLS = ("clang-19", "llvm-profdata-19")
"""What ``--coverage`` needs on PATH: the compiler of the instrumented node (``make coverage-node``) and the
tool that checks its raw profiles (Debian: clang-19, llvm-19)."""


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
    sandbox: str | None = None
    """Where vcan0 comes from (:data:`embedrl.hil.sandbox.MODES`); None: :data:`DEFAULT_SANDBOX` for the nodes
    that run in a sandbox."""
    timeout_ms: int | None = None
    """The node's watchdog; None: :data:`DEFAULT_TIMEOUT_MS` times the sandbox's slowdown."""
    inject: tuple[str, ...] = ()
    allow_faults: bool = False
    keep_work: bool = False
    fd: bool = False
    nodes: int = 1
    kill_node: tuple[int, int, int] | None = None
    """(node, episode, step): that node's process is killed before that step."""
    node: str = DEFAULT_NODE
    """The node's kind, a name of :data:`embedrl.hil.node_kinds.NODE_KINDS`."""
    target: str | None = None
    """The core the firmware node is built for (``node="firmware"``): a name of ``cortex_m/targets.mk``;
    None: :data:`DEFAULT_TARGET`."""
    trust_c: bool = False
    """Build and run the export's C even if it is not what embedrl generates from its ONNX (hand-edited)."""
    coverage: Path | None = None
    """A folder for the node's coverage (new, or an earlier coverage run's, replaced): the C node is built
    with clang's coverage flags (``make coverage-node``), runs in the sandbox as the plain node does, and
    each of its processes writes its raw profile when it exits; the profiles and the instrumented binary are
    kept here. None: a plain node."""

    @property
    def sandbox_mode(self) -> str:
        """Where vcan0 comes from: ``sandbox``, or :data:`DEFAULT_SANDBOX`."""
        return self.sandbox or DEFAULT_SANDBOX

    @property
    def firmware_target(self) -> str:
        """The core the firmware node is built for: ``target``, or :data:`DEFAULT_TARGET`."""
        return self.target or DEFAULT_TARGET

    def given(self, name: str) -> bool:
        """Whether the option ``name`` was set to something other than its default."""
        default = next(f.default for f in fields(self) if f.name == name)
        return bool(getattr(self, name) != default)

    @classmethod
    def of(cls, values: dict[str, Any]) -> RunOptions:
        """The options among ``values`` (e.g. parsed command-line arguments; other keys are ignored)."""
        known = {f.name for f in fields(cls)}
        picked = {k: v for k, v in values.items() if k in known}
        picked["inject"] = tuple(picked.get("inject", ()))
        return cls(**picked)
