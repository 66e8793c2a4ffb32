"""The kinds of policy node a HIL run drives (``--node``), one :class:`NodeKind` each in :data:`NODE_KINDS`.

A kind is data and one hook: what it needs and refuses (checked before anything is built), how the host
prepares it (an in-process node, a host binary, a firmware image), which clock it runs on, how the report
names where its C ran, and :attr:`NodeKind.start`, which starts one node inside the session (in a sandbox
guest, from the session's settings). Everything else asks these fields; no module compares a kind's name.
"""

from __future__ import annotations

from collections.abc import Callable, Mapping
from dataclasses import dataclass, field
from pathlib import Path
from typing import TYPE_CHECKING, Protocol

import numpy as np

if TYPE_CHECKING:
    from embedrl.hil.nodes import PolicyNode
    from embedrl.train.interface import Interface

Policy = Callable[[np.ndarray], np.ndarray]


class NodeSettings(Protocol):
    """What starting a node reads from the session's settings (:class:`embedrl.hil.session.SessionConfig`)."""

    @property
    def node_binary(self) -> str | None: ...
    @property
    def qemu_machine(self) -> str | None: ...
    @property
    def tick_instructions(self) -> float: ...
    @property
    def firmware_link(self) -> str | None: ...
    @property
    def firmware_control(self) -> str | None: ...
    @property
    def bus(self) -> str: ...
    @property
    def iface(self) -> str: ...
    @property
    def node_timeout_ms(self) -> int: ...
    @property
    def node_recover(self) -> int: ...
    @property
    def results(self) -> str: ...
    @property
    def fd(self) -> bool: ...
    @property
    def coverage_profile(self) -> str | None: ...


Start = Callable[[NodeSettings, "Interface", int, Callable[[], Policy]], "PolicyNode"]
"""Starts node ``node_id`` of a session: ``(settings, interface, node_id, reference policy factory)``."""


@dataclass(frozen=True)
class NodeKind:
    """A kind of node (``--node``): what it needs and refuses, how the host prepares it, how it starts."""

    called: str
    """How messages name it, e.g. ``the C node``."""
    help: str
    """What it is, for ``hil run --help``."""
    start: Start
    """Starts one node in the session (the settings name the binary, bus and watchdog)."""
    tools: tuple[str, ...] = ()
    """Programs it needs on PATH, looked for before anything is built or booted."""
    refuses: Mapping[str, str] = field(default_factory=dict)
    """Options (:class:`~embedrl.hil.options.RunOptions` fields) it cannot honour, each with the reason."""
    simulated_time: bool = False
    """Whether its clock is the simulation's (the firmware node): its watchdog is not stretched for a slow
    sandbox, and must exceed the sample time, which passes for it at every step."""
    builds_c: bool = True
    """Whether the run compiles the export's C and runs it (on this machine's kernel in a sandbox that shares
    its files, or on QEMU with semihosting): only C that is the generator's output, unless ``--trust-c``."""
    in_sandbox: bool = True
    """Whether it runs in a sandbox that provides vcan0; False: in this process on python-can's virtual
    bus."""
    host_binary: bool = False
    """Whether the host builds the node as a program for this machine (``make -C runtime_c node``) before the
    sandbox boots; a firmware image is built inside the session's sandbox, with its watchdog."""
    firmware_image: bool = False
    """Whether it is a Cortex-M image for ``--target`` on QEMU: its report carries ``firmware`` (instructions,
    stack) and ``target``."""
    own_socketcan: bool = False
    """Whether it has its own kernel CAN interface (the faults that act on one need it)."""
    runs_on: str = ""
    """Where its C runs, as the deployment report names it (``{target}``: the run's target); empty: no C."""

    def where(self, target: str | None) -> str:
        """Where this kind's C ran in a run on ``target``, for the deployment report."""
        return self.runs_on.format(target=target)


def _start_python(
    cfg: NodeSettings, interface: Interface, node_id: int, policy: Callable[[], Policy]
) -> PolicyNode:
    import can

    from embedrl.hil.nodes import PythonNode

    return PythonNode(
        lambda: can.Bus(interface=cfg.bus, channel=cfg.iface, receive_own_messages=False, fd=cfg.fd),
        interface, policy(), cfg.node_timeout_ms, cfg.node_recover, node_id, cfg.fd,
    )  # fmt: skip


def _start_c(
    cfg: NodeSettings, interface: Interface, node_id: int, policy: Callable[[], Policy]
) -> PolicyNode:
    from embedrl.hil.nodes import CNode

    if cfg.node_binary is None:
        raise ValueError("the C node needs node_binary")
    return CNode(
        cfg.node_binary, cfg.iface, cfg.node_timeout_ms, cfg.node_recover, node_id, cfg.coverage_profile
    )


def _start_firmware(
    cfg: NodeSettings, interface: Interface, node_id: int, policy: Callable[[], Policy]
) -> PolicyNode:
    import can

    from embedrl.export.contract.layout import episode_start_id, layout
    from embedrl.hil.firmware import FirmwareNode, HostQemu

    if cfg.node_binary is None:
        raise ValueError("the firmware node needs node_binary")
    if cfg.qemu_machine is None:
        raise ValueError("the firmware node needs qemu_machine")
    plan = layout(interface, node_id, cfg.fd)
    on_host = None
    if cfg.firmware_link is not None and cfg.firmware_control is not None:
        on_host = HostQemu(Path(cfg.firmware_control), cfg.firmware_link)
    return FirmwareNode(
        cfg.node_binary, cfg.qemu_machine,
        lambda: can.Bus(interface=cfg.bus, channel=cfg.iface, receive_own_messages=False),
        Path(cfg.results).with_name(f"firmware-uart1-node{node_id}.txt"),
        [frame_id for _, frame_id, _ in plan.observation]
        + ([episode_start_id(node_id)] if interface.state_size else []),
        on_host, cfg.tick_instructions,
    )  # fmt: skip


ONE_BOARD = "the firmware node runs one robot on one emulated board"
DEFAULT_NODE = "c"
"""The kind ``hil run`` drives unless ``--node`` names another: the verdict."""
NODE_KINDS: dict[str, NodeKind] = {
    "c": NodeKind(
        called="the C node",
        help="the compiled node over SocketCAN vcan0 (the verdict)",
        start=_start_c,
        refuses={"target": "the C node runs on this machine; --target picks the firmware node's core"},
        host_binary=True,
        own_socketcan=True,
        runs_on="C on the host",
    ),
    "firmware": NodeKind(
        called="the firmware node",
        help="the node as Cortex-M firmware on qemu-system-arm, its UART bridged to vcan0 as serial CAN "
        "(SLCAN), with instructions per step (processor in the loop)",
        start=_start_firmware,
        tools=("arm-none-eabi-gcc", "qemu-system-arm"),
        refuses={
            "fd": "the firmware node speaks classic CAN over its serial line (SLCAN)",
            "nodes": ONE_BOARD,
            "kill_node": ONE_BOARD,
            "coverage": "the firmware image is built by arm-none-eabi-gcc and runs on QEMU; clang's coverage "
            "measures the C node (--node c)",
        },
        simulated_time=True,
        firmware_image=True,
        runs_on="C on {target}",
    ),
    "python": NodeKind(
        called="the Python node",
        help="the Python reference node on python-can's virtual bus (no kernel, no build: the harness logic "
        "only)",
        start=_start_python,
        refuses={
            "sandbox": "the Python node runs in this process on python-can's virtual bus, in no sandbox",
            "target": "the Python node runs in this process; --target picks the firmware node's core",
            "trust_c": "the Python node runs the export's ONNX, no C",
            "coverage": "the Python node runs the export's ONNX, no C",
        },
        builds_c=False,
        in_sandbox=False,
    ),
}
"""Every node kind; an option a kind does not refuse applies to it (tests/hil checks each pair)."""


def kinds_with(flag: str) -> tuple[str, ...]:
    """The kinds whose boolean field ``flag`` is set, e.g. ``own_socketcan``: what a refusal suggests."""
    return tuple(name for name, kind in NODE_KINDS.items() if getattr(kind, flag))


def cli_help() -> str:
    """``--node``'s help: every kind and what it is."""
    return "; ".join(f"{name}: {kind.help}" for name, kind in NODE_KINDS.items())
