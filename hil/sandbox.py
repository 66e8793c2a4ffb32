"""Provisioning virtual SocketCAN: the host's vcan0, a new one, or a User-Mode Linux guest.

``auto``: use ``vcan0`` if the host has it; else create it if the kernel allows (root and the vcan
module); else run the session inside User-Mode Linux, whose own 6.1 kernel has SocketCAN, with the
host's root as its file system (so the project, its .venv and the built node are all there).
Results and the exit status come back through files in a work folder, never through UML's exit code.
"""

from __future__ import annotations

import os
import shlex
import shutil
import subprocess
import sys
from pathlib import Path

from hil.errors import HilError

IFACE = "vcan0"
UML_BINARY = "linux.uml"
UML_MEMORY = "1G"
UML_TIMEOUT_S = 3600
CAN_MODULES = (
    "net/can/can.ko",
    "net/can/can-raw.ko",
    "drivers/net/can/dev/can-dev.ko",
    "drivers/net/can/vcan.ko",
)
"""Loaded in this order inside the guest (vcan needs can-dev)."""


def host_has_vcan(iface: str = IFACE) -> bool:
    if Path(f"/sys/class/net/{iface}").exists():
        return True
    if shutil.which("ip") is None:
        return False
    created = subprocess.run(["ip", "link", "add", "dev", iface, "type", "vcan"], capture_output=True)
    if created.returncode != 0:
        return False
    return subprocess.run(["ip", "link", "set", "up", iface], capture_output=True).returncode == 0


def choose(sandbox: str) -> str:
    """``host`` or ``uml`` for the requested mode; a clear error if neither works."""
    if sandbox not in ("auto", "host", "uml"):
        raise HilError(f"unknown sandbox {sandbox!r}; use auto, host or uml")
    if sandbox in ("auto", "host") and host_has_vcan():
        return "host"
    if sandbox == "host":
        raise HilError(
            f"no {IFACE} on this host and it cannot be created (no kernel CAN support); use --sandbox uml"
        )
    if shutil.which(UML_BINARY) is None:
        raise HilError(
            f"no {IFACE} on this host and no User-Mode Linux ({UML_BINARY}): install the Debian packages "
            "user-mode-linux and kmod"
        )
    return "uml"


def run_in_uml(argv: list[str], workdir: Path, cwd: Path) -> int:
    """Run ``argv`` inside a User-Mode Linux guest with vcan0 up; return its exit status."""
    workdir.mkdir(parents=True, exist_ok=True)
    status_file = workdir / "uml_status"
    status_file.unlink(missing_ok=True)
    script = workdir / "uml_init.sh"
    modules = " ".join(f"$M/{m}" for m in CAN_MODULES)
    script.write_text(f"""#!/bin/sh
# PID 1 of the User-Mode Linux guest, written by embedrl (hil/sandbox.py).
mount -t proc proc /proc
mount -t sysfs sys /sys
mount -t tmpfs tmpfs /dev/shm
M=/usr/lib/uml/modules/$(uname -r)/kernel
for m in {modules}; do insmod "$m" || echo "insmod $m failed"; done
ip link add dev {IFACE} type vcan && ip link set up {IFACE}
export HOME={shlex.quote(os.environ.get("HOME", "/root"))}
export PATH={shlex.quote(os.environ.get("PATH", "/usr/bin:/bin"))}
export PYTHONUNBUFFERED=1
cd {shlex.quote(str(cwd))}
{" ".join(shlex.quote(a) for a in argv)}
echo $? > {shlex.quote(str(status_file))}
sync
poweroff -f
""")
    script.chmod(0o755)
    console = workdir / "uml_console.log"
    cmd = [
        UML_BINARY,
        f"mem={UML_MEMORY}",
        "rootfstype=hostfs",
        "rootflags=/",
        "rw",
        f"init={script}",
        "con=null",
        "con0=fd:0,fd:1",
    ]
    with console.open("wb") as out:
        try:
            subprocess.run(
                cmd, stdin=subprocess.DEVNULL, stdout=out, stderr=subprocess.STDOUT, timeout=UML_TIMEOUT_S
            )
        except subprocess.TimeoutExpired:
            raise HilError(
                f"the User-Mode Linux session did not finish within {UML_TIMEOUT_S} s ({console})"
            ) from None
    if not status_file.is_file():
        raise HilError(f"the User-Mode Linux session ended without a result; see {console}")
    return int(status_file.read_text().strip() or "1")


def python() -> str:
    return sys.executable
