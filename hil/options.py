"""What ``embedrl hil run`` is asked to do, as one frozen record (:class:`RunOptions`)."""

from __future__ import annotations

from collections.abc import Mapping
from dataclasses import dataclass, field, fields
from pathlib import Path
from typing import Any

from embedrl.export.contract.layout import WATCHDOG_MS

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


@dataclass(frozen=True)
class NodeKind:
    """A kind of node (``--node``): the programs it needs and the run's options that do not apply to it."""

    tools: tuple[str, ...] = ()
    """Programs it needs on PATH, looked for before anything is built or booted."""
    refuses: Mapping[str, str] = field(default_factory=dict)
    """Options (:class:`RunOptions` fields) it cannot honour, each with the reason."""
    simulated_time: bool = False
    """Whether its clock is the simulation's (the firmware node): its watchdog is not stretched for a slow
    sandbox, and must exceed the sample time, which passes for it at every step."""
    builds_c: bool = True
    """Whether the run compiles the export's C and runs it (on this machine's kernel in a sandbox that shares
    its files, or on QEMU with semihosting): only C that is the generator's output, unless ``--trust-c``."""


ONE_BOARD = "the firmware node runs one robot on one emulated board"
COVERAGE_TOOLS = ("clang-19", "llvm-profdata-19")
"""What ``--coverage`` needs on PATH: the compiler of the instrumented node (``make coverage-node``) and the
tool that checks its raw profiles (Debian: clang-19, llvm-19)."""
NODE_KINDS: dict[str, NodeKind] = {
    "c": NodeKind(
        refuses={"target": "the C node runs on this machine; --target picks the firmware node's core"}
    ),
    "firmware": NodeKind(
        tools=("arm-none-eabi-gcc", "qemu-system-arm"),
        refuses={
            "fd": "the firmware node speaks classic CAN over its serial line (SLCAN)",
            "nodes": ONE_BOARD,
            "kill_node": ONE_BOARD,
            "coverage": "the firmware image is built by arm-none-eabi-gcc and runs on QEMU; clang's coverage "
            "measures the C node (--node c)",
        },
        simulated_time=True,
    ),
    "python": NodeKind(
        refuses={
            "sandbox": "the Python node runs in this process on python-can's virtual bus, in no sandbox",
            "target": "the Python node runs in this process; --target picks the firmware node's core",
            "trust_c": "the Python node runs the export's ONNX, no C",
            "coverage": "the Python node runs the export's ONNX, no C",
        },
        builds_c=False,
    ),
}
"""Every node kind; an option a kind does not refuse applies to it (tests/hil checks each pair)."""


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
    node: str = "c"
    """``c``: the compiled node over SocketCAN; ``firmware``: the Cortex-M image on QEMU, bridged over
    SLCAN; ``python``: the reference node on a virtual bus."""
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
