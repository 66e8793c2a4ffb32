"""The ``uml`` provider: a User-Mode Linux kernel, whose own SocketCAN gives ``vcan0``.

The guest's root file system is the host's ``/`` (hostfs, read-write), so the project, its virtual
environment and the built node are all there. Two kinds of kernel, tried in this order:

- Debian's packaged ``user-mode-linux`` (``/usr/bin/linux.uml``, 6.1 on bookworm);
- the newer ones ``make deps`` caches in ``<cache>/uml/<version>/`` (:mod:`hil.sandbox.provision`):
  UML before 7.2 dies on hosts whose CPU has AMX (the host rejects its FPU state), 7.2 runs there.
"""

from __future__ import annotations

import json
import os
import shlex
import shutil
import socket
import subprocess
from dataclasses import dataclass
from pathlib import Path

from embedrl.common import SYSTEM_TOOL_DIRS, system_tool
from embedrl.hil.sandbox.base import VCAN_UP, Guest, Provider, SerialLink, VmGuest

PACKAGED_BINARY = "linux.uml"
PACKAGED_MODULES = Path("/usr/lib/uml/modules")
MEMORY = "1G"
BOOT_TIMEOUT_S = 60.0
CAN_MODULES = (
    "net/can/can.ko",
    "net/can/can-raw.ko",
    "drivers/net/can/dev/can-dev.ko",
    "drivers/net/can/vcan.ko",
)
"""Loaded in this order inside the guest (vcan needs can-dev)."""
GUEST_TOOLS = ("insmod", "ip")
"""The host's programs the guest's set-up runs (its PATH includes :data:`SYSTEM_TOOL_DIRS`)."""
MANIFEST = "manifest.json"
LINK_LINE = 1
"""The guest's serial line ``ttyS1`` carries :attr:`Guest.link`: its host end is one end of a socket pair
this process keeps (UML's ``ssl1=fd:N``), so the firmware's emulator runs on the host at full speed."""


def cache_root() -> Path:
    """Where downloaded sandbox kernels live: ``$EMBEDRL_CACHE``, else ``~/.cache/embedrl``."""
    explicit = os.environ.get("EMBEDRL_CACHE")
    if explicit:
        return Path(explicit)
    xdg = os.environ.get("XDG_CACHE_HOME")
    return (Path(xdg) if xdg else Path.home() / ".cache") / "embedrl"


@dataclass(frozen=True)
class UmlKernel:
    binary: Path
    modules: Path
    """Holds ``<kernel release>/kernel/...``; the guest picks its release with ``uname -r``."""
    origin: str
    """``Debian package 6.1um4+b13`` or ``7.2um1, cached``."""


class UmlProvider(Provider):
    name = "uml"

    def __init__(self, kernel: UmlKernel) -> None:
        self.kernel = kernel
        self.label = f"uml ({kernel.origin})"

    def missing(self) -> str | None:
        if not self.kernel.binary.is_file():
            return f"no User-Mode Linux kernel at {self.kernel.binary} (`make deps` installs one)"
        missing = [tool for tool in GUEST_TOOLS if system_tool(tool) is None]
        if missing:
            return (
                f"the guest needs {' and '.join(missing)} from the host (Debian kmod, iproute2), found "
                f"neither on PATH nor in {', '.join(SYSTEM_TOOL_DIRS)}"
            )
        return None

    def boot(self, workdir: Path) -> Guest:
        workdir.mkdir(parents=True, exist_ok=True)
        modules = " ".join(f'"$M/{m}"' for m in CAN_MODULES)
        setup = f"""mount -t proc proc /proc
mount -t sysfs sys /sys
mount -t tmpfs tmpfs /dev/shm
mkdir -p /dev/pts && (mountpoint -q /dev/pts || mount -t devpts -o ptmxmode=0666 devpts /dev/pts)
[ -e /dev/ptmx ] || ln -s pts/ptmx /dev/ptmx
M={shlex.quote(str(self.kernel.modules))}/$(uname -r)/kernel
for m in {modules}; do insmod "$m" || echo "embedrl: insmod $m failed"; done
{VCAN_UP}"""
        command = [
            str(self.kernel.binary),
            f"mem={MEMORY}",
            "rootfstype=hostfs",
            "rootflags=/",
            "rw",
            f"init={workdir / 'guest.sh'}",
            "con=null",
            "con0=fd:0,fd:1",
        ]
        host_end, guest_end = socket.socketpair()
        command += ["ssl=null", f"ssl{LINK_LINE}=fd:{guest_end.fileno()}"]
        try:
            guest = VmGuest(
                "uml",
                f"uml: User-Mode Linux ({self.kernel.origin})",
                command,
                workdir,
                setup,
                "poweroff -f",
                BOOT_TIMEOUT_S,
                pass_fds=(guest_end.fileno(),),
            )
        except BaseException:
            host_end.close()
            raise
        finally:
            guest_end.close()  # the guest holds its end now
        guest.link = SerialLink(host_end, f"/dev/ttyS{LINK_LINE}")
        guest.description = f"uml: User-Mode Linux {guest.kernel} ({self.kernel.origin})"
        return guest


def packaged_kernel() -> UmlKernel | None:
    binary = shutil.which(PACKAGED_BINARY)
    if binary is None:
        return None
    query = subprocess.run(
        ["dpkg-query", "-W", "-f", "${Version}", "user-mode-linux"], capture_output=True, text=True
    )
    version = query.stdout.strip() if query.returncode == 0 else "unknown version"
    return UmlKernel(Path(binary), PACKAGED_MODULES, f"Debian package {version}")


def cached_kernels(root: Path | None = None) -> list[UmlKernel]:
    """The kernels :mod:`hil.sandbox.provision` verified and cached, newest version first."""
    kernels = []
    for manifest in sorted((root or cache_root()).glob(f"uml/*/{MANIFEST}"), reverse=True):
        try:
            data = json.loads(manifest.read_text())
            binary, modules, version = data["binary"], data["modules"], data["version"]
        except (OSError, ValueError, KeyError, TypeError):
            continue  # an unreadable manifest is a cache that was never completed
        folder = manifest.parent
        kernels.append(UmlKernel(folder / binary, folder / modules, f"{version}, cached"))
    return kernels


def uml_providers() -> list[UmlProvider]:
    packaged = packaged_kernel()
    kernels = ([packaged] if packaged else []) + cached_kernels()
    if not kernels:
        return [UmlProvider(UmlKernel(Path("/usr/bin") / PACKAGED_BINARY, PACKAGED_MODULES, "not installed"))]
    return [UmlProvider(k) for k in kernels]
