"""The ``host`` provider: ``vcan0`` on the machine itself (any Linux with the ``vcan`` module)."""

from __future__ import annotations

import subprocess
import sys
from pathlib import Path

from embedrl.common import system_tool
from embedrl.hil.sandbox.base import IFACE, Guest, JobResult, Provider, SandboxError


class HostGuest(Guest):
    """Commands run directly on the host, where ``vcan0`` is up."""

    provider = "host"
    boot_s = 0.0
    python = sys.executable

    def __init__(self) -> None:
        self.description = f"host: {IFACE} on this machine's kernel"

    def run(self, argv: list[str], cwd: Path, timeout_s: float) -> JobResult:
        try:
            done = subprocess.run(
                argv, cwd=cwd, stdout=subprocess.PIPE, stderr=subprocess.STDOUT, timeout=timeout_s
            )
        except subprocess.TimeoutExpired:
            raise SandboxError(f"`{' '.join(argv)}` gave no result within {timeout_s:.0f} s") from None
        return JobResult(done.returncode, done.stdout.decode(errors="replace"))


class HostProvider(Provider):
    name = "host"
    label = "host"

    def missing(self) -> str | None:
        if Path(f"/sys/class/net/{IFACE}").exists():
            return None
        ip = system_tool("ip")
        if ip is None:
            return f"no {IFACE} on this host and no `ip` command to create it (Debian iproute2)"
        created = subprocess.run([ip, "link", "add", "dev", IFACE, "type", "vcan"], capture_output=True)
        if created.returncode != 0:
            said = created.stderr.decode(errors="replace").strip() or f"status {created.returncode}"
            return f"no {IFACE} on this host and it cannot be created (`ip link add ... type vcan`: {said})"
        up = subprocess.run([ip, "link", "set", "up", IFACE], capture_output=True)
        if up.returncode != 0:
            return (
                f"{IFACE} was created but cannot be brought up: {up.stderr.decode(errors='replace').strip()}"
            )
        return None

    def boot(self, workdir: Path) -> Guest:
        return HostGuest()
