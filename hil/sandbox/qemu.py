"""The ``qemu`` provider: a QEMU virtual machine running Debian's stable kernel, through virtme-ng.

virtme-ng (``vng``) boots the kernel with the host's ``/`` shared read-only (the guest's work folder is
shared writable), so the project and its virtual environment are there as in the ``uml`` provider. It
depends on no unstable package and no CPU quirk of UML: the independent second route. KVM is tried
first where ``/dev/kvm`` is usable; where a KVM guest fails (nested virtualisation), pure emulation
(TCG) boots in about 20 s and runs Python about ten times slower than the host.
"""

from __future__ import annotations

import os
import re
import shutil
import sys
from pathlib import Path

from embedrl.hil.sandbox.base import VCAN_UP, Guest, Provider, SandboxError, VmGuest

KERNELS = Path("/boot")
MODULES = Path("/lib/modules")
VCAN_MODULE = "kernel/drivers/net/can/vcan.ko"
MEMORY = "2G"
CPUS = 2
KVM_BOOT_TIMEOUT_S = 30.0
"""A KVM guest boots in seconds; one that takes longer has hung (seen with nested virtualisation)."""
TCG_BOOT_TIMEOUT_S = 300.0
SETUP = f"""for m in can can-raw vcan; do modprobe "$m" || echo "embedrl: modprobe $m failed"; done
mkdir -p /dev/shm && (mountpoint -q /dev/shm || mount -t tmpfs tmpfs /dev/shm)
mkdir -p /dev/pts && (mountpoint -q /dev/pts || mount -t devpts -o ptmxmode=0666 devpts /dev/pts)
[ -e /dev/ptmx ] || ln -s pts/ptmx /dev/ptmx
{VCAN_UP}"""


def vng_binary() -> Path | None:
    """virtme-ng's ``vng``: beside this Python (the project's virtual environment) or on PATH."""
    beside = Path(sys.executable).parent / "vng"
    if beside.is_file():
        return beside
    found = shutil.which("vng")
    return Path(found) if found else None


def debian_kernel() -> tuple[Path, str] | None:
    """The newest ``/boot/vmlinuz-*`` whose modules include vcan, and its release."""

    def version_key(path: Path) -> list[int]:
        return [int(n) for n in re.findall(r"\d+", path.name)]

    for image in sorted(KERNELS.glob("vmlinuz-*"), key=version_key, reverse=True):
        release = image.name.removeprefix("vmlinuz-")
        if (MODULES / release / VCAN_MODULE).is_file():
            return image, release
    return None


def kvm_usable() -> bool:
    return os.access("/dev/kvm", os.R_OK | os.W_OK)


TCG_SLOWDOWN = 10.0
"""Python under pure emulation (TCG) runs about ten times slower than on the host (platform notes: a
2M-iteration loop takes 1.36 s vs 0.13 s)."""


class QemuProvider(Provider):
    name = "qemu"
    label = "qemu (virtme-ng, Debian linux-image-amd64)"

    def missing(self) -> str | None:
        if vng_binary() is None:
            return "virtme-ng (vng) is not installed (PyPI virtme-ng; `make setup`)"
        if shutil.which("qemu-system-x86_64") is None:
            return "qemu-system-x86_64 is not installed (Debian qemu-system-x86; `make deps`)"
        kernel = debian_kernel()
        if kernel is None:
            return "no kernel with the vcan module in /boot (Debian linux-image-amd64; `make deps`)"
        if not os.access(kernel[0], os.R_OK):
            return f"{kernel[0]} is not readable by this user (Debian makes kernel images root-only)"
        return None

    def boot(self, workdir: Path) -> Guest:
        workdir.mkdir(parents=True, exist_ok=True)
        found = debian_kernel()
        vng = vng_binary()
        if found is None or vng is None:
            raise SandboxError(self.missing() or "qemu provider unavailable")
        image, release = found
        env = dict(os.environ)
        env["PATH"] = f"{vng.parent}{os.pathsep}{env.get('PATH', '')}"  # vng runs virtme-run from PATH
        kvm_failure = None
        if kvm_usable():
            try:
                return self._boot(vng, image, release, workdir / "kvm", env, kvm=True)
            except SandboxError as exc:
                why = exc.diagnosis
                kvm_failure = f"{why.cause}: {why.evidence[-1]}" if why and why.evidence else str(exc)
        guest = self._boot(vng, image, release, workdir / "tcg", env, kvm=False)
        if kvm_failure:
            guest.description += f"; KVM failed first ({kvm_failure})"
        return guest

    def _boot(
        self, vng: Path, image: Path, release: str, workdir: Path, env: dict[str, str], kvm: bool
    ) -> VmGuest:
        workdir.mkdir(parents=True, exist_ok=True)
        mode = "KVM" if kvm else "TCG emulation"
        command = [
            str(vng),
            "--run",
            str(image),
            "--rwdir",
            str(workdir),
            "--memory",
            MEMORY,
            "--cpus",
            str(CPUS),
            *([] if kvm else ["--disable-kvm"]),
            "--exec",
            f"sh {workdir / 'guest.sh'}",
        ]
        guest = VmGuest(
            "qemu",
            f"qemu: Linux {release} under QEMU ({mode}, virtme-ng)",
            command,
            workdir,
            SETUP,
            "true",
            KVM_BOOT_TIMEOUT_S if kvm else TCG_BOOT_TIMEOUT_S,
            env=env,
        )
        guest.slowdown = 1.0 if kvm else TCG_SLOWDOWN
        return guest
