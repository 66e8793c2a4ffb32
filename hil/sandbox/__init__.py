"""A real SocketCAN ``vcan0`` on any Linux machine: the host's own, or one inside a guest kernel.

Three providers behind one interface (:data:`PROVIDERS`), tried in this order by ``auto``:

==========  =============================================================================  ============
provider    what gives the CAN link                                                        boot
==========  =============================================================================  ============
``host``    ``vcan0`` on the host (exists, or created: root and the ``vcan`` module)       none
``uml``     a User-Mode Linux kernel with the host's ``/`` as its root: Debian's packaged   ~1.5 s
            one, then the newer one ``make deps`` caches (UML < 7.2 dies on AMX CPUs)
``qemu``    a QEMU virtual machine (virtme-ng) with Debian's stable ``linux-image-amd64``   ~20 s (TCG)
            and the host's ``/`` shared read-only; KVM when it works, else pure emulation
==========  =============================================================================  ============

A provider counts as working only after its self-test: the guest boots, loads the CAN modules, brings
``vcan0`` up and a probe sends a frame through an ``AF_CAN`` socket and receives it
(:mod:`hil.sandbox.probe`). A guest then serves any number of commands (:meth:`Guest.run`), so a test
session boots each guest once. A guest that dies is diagnosed from its console log
(:mod:`hil.sandbox.console`) and ``auto`` moves on to the next provider.
"""

from __future__ import annotations

import time
from collections.abc import Callable, Iterator
from contextlib import contextmanager
from dataclasses import dataclass
from pathlib import Path

from embedrl.hil.errors import HilError
from embedrl.hil.sandbox.base import REPO, Guest, Provider, SandboxError
from embedrl.hil.sandbox.host import HostProvider
from embedrl.hil.sandbox.qemu import QemuProvider
from embedrl.hil.sandbox.uml import uml_providers


@dataclass(frozen=True)
class SandboxProvider:
    """One way to get ``vcan0`` (``--sandbox NAME``): its candidates on this machine and what it needs."""

    name: str
    summary: str
    """What it is, for the commands' help."""
    candidates: Callable[[], list[Provider]]
    """Its variants found on this machine, in the order they are tried (UML: Debian's, then cached)."""
    debian: tuple[str, ...]
    """The Debian packages it needs (``make deps`` installs them: :func:`debian_packages`)."""


PROVIDERS = (
    SandboxProvider("host", "the host's own vcan0", lambda: [HostProvider()], ("kmod", "iproute2")),
    SandboxProvider(
        "uml",
        "a User-Mode Linux kernel",
        lambda: [*uml_providers()],
        ("user-mode-linux", "kmod", "iproute2", "patchelf"),
    ),
    SandboxProvider(
        "qemu",
        "a QEMU virtual machine (virtme-ng)",
        lambda: [QemuProvider()],
        ("qemu-system-x86", "busybox-static", "linux-image-amd64"),
    ),
)
"""Every sandbox provider, in the order ``auto`` tries them."""
AUTO = "auto"
"""The mode that tries every provider in turn."""
MODES = (AUTO, *(p.name for p in PROVIDERS))
PROBE_TIMEOUT_S = 60.0
"""The self-test probe is one short Python process (slower under QEMU's pure emulation)."""

__all__ = [
    "AUTO",
    "MODES",
    "PROVIDERS",
    "Guest",
    "Provider",
    "ProviderCheck",
    "SandboxError",
    "SandboxProvider",
    "check",
    "debian_packages",
    "mode_help",
    "open_guest",
    "providers",
    "select",
]


@dataclass(frozen=True)
class ProviderCheck:
    """One provider's self-test on this machine."""

    provider: str
    label: str
    works: bool
    boot_s: float | None
    reason: str


def providers(mode: str) -> list[Provider]:
    """The candidate providers for ``mode``, in the order ``auto`` tries them."""
    if mode not in MODES:
        raise HilError(f"unknown sandbox {mode!r}; use one of {', '.join(MODES)}")
    return [found for p in PROVIDERS if mode in (AUTO, p.name) for found in p.candidates()]


def mode_help() -> str:
    """What ``--sandbox`` chooses between, for the commands' help."""
    names = ", ".join(p.name for p in PROVIDERS)
    each = "; ".join(f"{p.name}: {p.summary}" for p in PROVIDERS)
    return f"{AUTO}: the first of {names} that passes its self-test; {each}"


def debian_packages() -> tuple[str, ...]:
    """The Debian packages every provider needs, each once (``make apt-packages`` installs them)."""
    return tuple(dict.fromkeys(package for p in PROVIDERS for package in p.debian))


def open_guest(provider: Provider, workdir: Path) -> Guest:
    """Boot ``provider`` and run its self-test; the guest is closed again if the test fails."""
    reason = provider.missing()
    if reason:
        raise SandboxError(reason)
    guest = provider.boot(workdir)
    try:
        result = guest.run(
            [guest.python, "-m", "embedrl.hil.sandbox.probe", guest.iface], REPO, timeout_s=PROBE_TIMEOUT_S
        )
        if result.status != 0:
            raise SandboxError(
                guest.diagnose(f"the self-test failed (status {result.status}): {result.last_lines()}")
            )
    except BaseException:
        guest.close()
        raise
    return guest


def select(mode: str, workdir: Path, say: Callable[[str], None] = print) -> Guest:
    """The first provider for ``mode`` that passes its self-test; ``say`` reports the choice and skips."""
    skipped: list[str] = []
    for provider in providers(mode):
        try:
            guest = open_guest(provider, workdir / provider.slug)
        except SandboxError as exc:
            skipped.append(f"{provider.label}: {exc}")
            continue
        say(f"sandbox: {guest.description} (self-test passed, boot {guest.boot_s:.1f} s)")
        for line in skipped:
            say(f"  skipped {line}")
        return guest
    raise SandboxError(
        f"no CAN sandbox works on this machine (--sandbox {mode}): "
        + "; ".join(skipped)
        + ". Run `embedrl hil doctor` for details and `make deps` to install the providers"
    )


@contextmanager
def opened(mode: str, workdir: Path, say: Callable[[str], None] = print) -> Iterator[Guest]:
    """:func:`select` as a context manager that closes the guest."""
    guest = select(mode, workdir, say)
    try:
        yield guest
    finally:
        guest.close()


def check(provider: Provider, workdir: Path) -> ProviderCheck:
    """Boot ``provider``, run its self-test and shut it down again: one row of ``embedrl hil doctor``."""
    start = time.monotonic()
    try:
        guest = open_guest(provider, workdir / provider.slug)
    except SandboxError as exc:
        return ProviderCheck(provider.name, provider.label, False, None, str(exc))
    try:
        boot_s = guest.boot_s
        total = time.monotonic() - start
        return ProviderCheck(
            provider.name,
            provider.label,
            True,
            boot_s,
            f"{guest.description}; vcan0 up, AF_CAN frame round trip ok ({total:.1f} s in all)",
        )
    finally:
        guest.close()
