"""The provider interface, and the guest that runs the host's commands inside a virtual machine.

A virtual-machine guest (User-Mode Linux or QEMU) boots once, brings ``vcan0`` up, then runs the jobs
the host drops into a shared queue folder, one after another, until the host asks it to stop. Every
result (a job's exit status and output) comes back through that folder: a guest's own exit code says
nothing about the commands it ran. When the guest dies, its console log says why.
"""

from __future__ import annotations

import contextlib
import json
import os
import shlex
import signal
import socket
import subprocess
import sys
import tempfile
import time
from abc import ABC, abstractmethod
from dataclasses import dataclass
from pathlib import Path

from embedrl.common import SYSTEM_TOOL_DIRS
from embedrl.hil.errors import HilError
from embedrl.hil.sandbox.console import Diagnosis, diagnose
from embedrl.reaper import GroupReaper

REPO = Path(__file__).resolve().parents[2]
IFACE = "vcan0"
POLL_S = 0.02
STOP_TIMEOUT_S = 30.0
"""How long an idle guest may take to shut down after the host asked it to. A guest closed while a job
runs (the command was interrupted) is killed at once: it would not read the stop request until the
job ended."""
VCAN_UP = f"""if ip link add dev {IFACE} type vcan || [ -e /sys/class/net/{IFACE} ]; then
    ip link set {IFACE} mtu 72 || echo "embedrl: {IFACE} cannot carry CAN FD (mtu 72 refused)"
    ip link set up {IFACE} || echo "embedrl: no {IFACE} (ip link set up failed)"
else
    echo "embedrl: no {IFACE} (ip link add failed)"
fi"""
"""Guest shell code that brings ``vcan0`` up, CAN FD capable (MTU 72, classic frames pass as well), once
the CAN modules are loaded; failures go to the console."""
BUSY_POLLS = 40
"""Polls of the job queue, 50 ms apart, before an idle guest (its job server, or its shell loop) polls once
a second."""
SERVER_PRELOAD = ("embedrl.hil.session", "embedrl.hil.round_trip")
"""Programs whose jobs (``python -m`` one of them) run in a fork of the guest's job server
(:mod:`~embedrl.hil.sandbox.job_server`), which imports their dependencies once."""
SHELL_JOB = ".sh"
PYTHON_JOB = ".py.json"
"""A job is ``job-N.sh`` (a shell script) or ``job-N.py.json`` (``{"module", "args", "cwd", "env"}``); its
output goes to ``job-N.out``, its exit status to ``job-N.rc``."""
SERVER_FAILED = "job-server.failed"
"""Written by the guest's script when its job server ended before the host asked it to stop (its own shell
loop then runs the shell jobs); the server's output is in ``job-server.log``."""
SERVER_LOG = "job-server.log"
OUTPUT_LINES = 6
"""Lines of a failed job's output quoted in an error."""


class SandboxError(HilError):
    """No working CAN sandbox, or a guest that died (the message carries the diagnosis)."""

    def __init__(self, message: str | Diagnosis) -> None:
        super().__init__(str(message))
        self.diagnosis = message if isinstance(message, Diagnosis) else None


@dataclass(frozen=True)
class JobResult:
    status: int
    output: str

    def last_lines(self, n: int = OUTPUT_LINES) -> str:
        lines = [line.strip() for line in self.output.splitlines() if line.strip()]
        return " | ".join(lines[-n:]) or "no output"


@dataclass(frozen=True)
class SerialLink:
    """A serial line from this machine into the guest: ``host`` is this machine's end (a connected stream
    socket), ``device`` the guest's terminal for it. A program on this machine (the firmware's emulator)
    then talks to a program in the guest without running under the guest's kernel."""

    host: socket.socket
    device: str


class Guest(ABC):
    """A place where ``vcan0`` is up and commands run with the host's files visible."""

    provider: str
    """``host``, ``uml`` or ``qemu``."""
    description: str
    """What exactly runs, e.g. ``uml: User-Mode Linux 6.1.176 (Debian package)``."""
    boot_s: float
    iface: str = IFACE
    python: str = sys.executable
    slowdown: float = 1.0
    """How many times slower than the host a Python program runs in the guest: the node's default
    watchdog and the simulator's wait for an answer are stretched by it (pure emulation: ~10)."""
    link: SerialLink | None = None
    """A serial line from this machine into the guest (None: the guest has none; the firmware's emulator
    then runs inside it)."""

    @abstractmethod
    def run(self, argv: list[str], cwd: Path, timeout_s: float) -> JobResult:
        """Run ``argv`` in ``cwd`` inside the guest: its status and output; SandboxError if the guest dies."""

    def scratch(self) -> Path:
        """A new empty folder that both the host and the guest can write."""
        return Path(tempfile.mkdtemp(prefix="embedrl-hil-"))

    def diagnose(self, context: str) -> Diagnosis:
        """Why the guest failed, for an error message: ``context`` plus what the console says."""
        return Diagnosis("command-failed", f"{self.description}: {context}", ())

    def close(self) -> None:  # noqa: B027 (a guest without a machine has nothing to shut down)
        """Shut the guest down (idempotent)."""

    def __enter__(self) -> Guest:
        return self

    def __exit__(self, *exc: object) -> None:
        self.close()


class Provider(ABC):
    """A way to get a ``vcan0``: checked cheaply by :meth:`missing`, then booted."""

    name: str
    label: str
    """The provider and its variant, e.g. ``uml (Debian 6.1um4+b13)``, for reports."""

    @property
    def slug(self) -> str:
        """A folder name for this provider's work files."""
        return "".join(c if c.isalnum() or c in ".-" else "-" for c in self.label).strip("-")

    @abstractmethod
    def missing(self) -> str | None:
        """Why this provider cannot work here without trying to boot it (``None``: worth trying)."""

    @abstractmethod
    def boot(self, workdir: Path) -> Guest:
        """Start a guest with ``vcan0`` up; SandboxError with the diagnosis if it does not come up."""


class VmGuest(Guest):
    """A virtual machine started by ``command``, running ``guest.sh`` as its job loop.

    ``setup`` is the provider's shell code that loads the CAN modules and brings ``vcan0`` up (ending
    with :data:`VCAN_UP`), run before the guest reports ready; ``shutdown`` ends the guest after the
    loop (``poweroff -f`` for a UML PID 1).
    """

    def __init__(
        self,
        provider: str,
        description: str,
        command: list[str],
        workdir: Path,
        setup: str,
        shutdown: str,
        boot_timeout_s: float,
        env: dict[str, str] | None = None,
        pass_fds: tuple[int, ...] = (),
    ) -> None:
        """``pass_fds``: this process's descriptors the machine inherits (its serial lines' host ends)."""
        self.provider = provider
        self.description = description
        self.workdir = workdir
        self.queue = workdir / "queue"
        self.console = workdir / "console.log"
        self.closed = False
        self._busy = False
        self._jobs = 0
        self.queue.mkdir(parents=True, exist_ok=True)
        for stale in self.queue.iterdir():
            stale.unlink()
        script = workdir / "guest.sh"
        script.write_text(_guest_script(self.queue, setup, shutdown, self.python))
        script.chmod(0o755)
        self.script = script
        start = time.monotonic()
        with self.console.open("wb") as out:
            self.process = subprocess.Popen(
                [*command],
                stdin=subprocess.DEVNULL,
                stdout=out,
                stderr=subprocess.STDOUT,
                start_new_session=True,  # UML forks helpers: stop the whole group
                env=env,
                pass_fds=pass_fds,
            )
        self._reaper = GroupReaper(self.process.pid)  # the guest ends with this process, even on SIGKILL
        ready = self.queue / "ready"
        while not ready.is_file():
            if self.process.poll() is not None:
                self._kill()  # the helpers UML forked
                raise SandboxError(self._died("exited while booting"))
            if time.monotonic() - start > boot_timeout_s:
                self._kill()
                raise SandboxError(diagnose(self._log(), timed_out=True, timeout_s=boot_timeout_s))
            time.sleep(POLL_S)
        self.boot_s = time.monotonic() - start
        self.kernel = ready.read_text().strip()

    def run(self, argv: list[str], cwd: Path, timeout_s: float) -> JobResult:
        if self.closed:
            raise SandboxError(f"{self.description}: the guest is shut down")
        deadline = time.monotonic() + timeout_s
        env = {
            "HOME": os.environ.get("HOME", "/root"),
            "PATH": os.environ.get("PATH", "/usr/bin:/bin"),
            "PYTHONUNBUFFERED": "1",
            "PYTHONDONTWRITEBYTECODE": "1",
        }
        server = not (self.queue / SERVER_FAILED).exists()
        if server and argv[:2] == [self.python, "-m"] and argv[2] in SERVER_PRELOAD:
            name = self._next_job()
            job = {"module": argv[2], "args": argv[3:], "cwd": str(cwd), "env": env}
            tmp = self.queue / f"{name}.tmp"
            tmp.write_text(json.dumps(job))
            tmp.rename(self.queue / f"{name}{PYTHON_JOB}")  # the guest only picks up complete job files
            taken = self._result(name, argv, deadline, timeout_s, python=True)
            if taken is not None:
                return taken
        name = self._next_job()
        lines = [f"export {k}={shlex.quote(v)}" for k, v in env.items()]
        lines += [f"cd {shlex.quote(str(cwd))} || exit 125", shlex.join(argv)]
        tmp = self.queue / f"{name}.tmp"
        tmp.write_text("\n".join(lines) + "\n")
        tmp.rename(self.queue / f"{name}{SHELL_JOB}")
        return self._result(name, argv, deadline, timeout_s) or JobResult(1, "")

    def _next_job(self) -> str:
        self._jobs += 1
        return f"job-{self._jobs}"

    def _result(
        self, name: str, argv: list[str], deadline: float, timeout_s: float, python: bool = False
    ) -> JobResult | None:
        """Job ``name``'s status and output once it has ended; ``None`` for a Python job (``python``) the job
        server ended before taking (its file removed: the caller queues it for the guest's shell loop).
        SandboxError if the guest dies, the server ends while running a Python job, or ``deadline``
        passes."""
        status_file = self.queue / f"{name}.rc"
        python_job = self.queue / f"{name}{PYTHON_JOB}"
        self._busy = True
        while not status_file.is_file():
            if self.process.poll() is not None:
                self.closed = True
                raise SandboxError(self._died(f"died while running `{shlex.join(argv)}`"))
            failed = (
                _read(self.queue / SERVER_FAILED) if python else ""
            )  # a shell job: the shell loop runs it
            if failed:
                with contextlib.suppress(FileNotFoundError):
                    python_job.unlink()  # not taken yet
                    self._busy = False
                    return None
                if not status_file.is_file():
                    self._busy = False
                    raise SandboxError(
                        f"{self.description}: the guest's job server ended ({failed.strip()}) while "
                        f"running `{shlex.join(argv)}`; its log: {_read(self.queue / SERVER_LOG)[-300:]}"
                    )
            if time.monotonic() > deadline:
                self.closed = True
                self._kill()  # the guest is busy with the stuck job: it would not hear a stop request
                so_far = JobResult(0, _read(self.queue / f"{name}.out")).last_lines()
                raise SandboxError(
                    f"`{shlex.join(argv)}` gave no result within {timeout_s:.0f} s "
                    f"inside {self.description}; its output so far: {so_far}"
                )
            time.sleep(POLL_S)
        self._busy = False
        status = int(status_file.read_text().strip() or "1")
        return JobResult(status, _read(self.queue / f"{name}.out"))

    def scratch(self) -> Path:
        # A QEMU guest sees the host read-only except its work folder.
        return Path(tempfile.mkdtemp(prefix="run-", dir=self.workdir))

    def diagnose(self, context: str) -> Diagnosis:
        found = diagnose(self._log())
        if found.cause in ("unknown", "no-output"):
            return Diagnosis("command-failed", f"{self.description}: {context}", found.evidence)
        return Diagnosis(found.cause, f"{self.description}: {found.explanation}; {context}", found.evidence)

    def close(self) -> None:
        if self.closed and self.process.poll() is not None:
            return
        self.closed = True
        try:
            if not self._busy:  # an idle guest shuts down in order (its file systems synced)
                (self.queue / "stop").touch()
                with contextlib.suppress(subprocess.TimeoutExpired):
                    self.process.wait(timeout=STOP_TIMEOUT_S)
        finally:
            self._kill()  # always, even when a second signal interrupts the wait: helpers UML left behind
            if self.link is not None:
                self.link.host.close()

    def _died(self, what: str) -> Diagnosis:
        found = diagnose(self._log())
        return Diagnosis(
            found.cause,
            f"{self.description} {what} (exit status {self.process.returncode}): {found.explanation}",
            found.evidence,
        )

    def _log(self) -> str:
        return _read(self.console)

    def _kill(self) -> None:
        with contextlib.suppress(ProcessLookupError):
            os.killpg(self.process.pid, signal.SIGKILL)
        self.process.wait()
        self._reaper.release()


def _read(path: Path) -> str:
    try:
        return path.read_text(errors="replace")
    except FileNotFoundError:
        return ""


def _guest_script(queue: Path, setup: str, shutdown: str, python: str) -> str:
    q = shlex.quote(str(queue))
    server = shlex.join([python, "-m", "embedrl.hil.sandbox.job_server", str(queue), *SERVER_PRELOAD])
    return f"""#!/bin/sh
# Written by embedrl (hil/sandbox/base.py): set up (vcan0), then run the jobs the host puts in the queue.
Q={q}
PATH="${{PATH:+$PATH:}}{":".join(SYSTEM_TOOL_DIRS)}"
export PATH
{setup}
uname -r > "$Q/ready.tmp" && mv "$Q/ready.tmp" "$Q/ready"
# The job server (hil/sandbox/job_server.py) runs the jobs until the host asks it to stop; should it end
# before, this script's own loop runs the shell jobs.
PYTHONDONTWRITEBYTECODE=1 {server} > "$Q/{SERVER_LOG}" 2>&1
status=$?
[ -e "$Q/stop" ] || echo "exited with status $status" > "$Q/{SERVER_FAILED}"
idle=0
while [ ! -e "$Q/stop" ]; do
    idle=$((idle + 1))
    for job in "$Q"/job-*{SHELL_JOB}; do
        [ -e "$job" ] || continue
        n="${{job%{SHELL_JOB}}}"
        sh "$job" > "$n.out" 2>&1
        echo $? > "$n.rc.tmp" && mv "$n.rc.tmp" "$n.rc"
        rm -f "$job"
        idle=0
    done
    # every 50 ms while jobs come; once idle for {BUSY_POLLS} polls, every second (a poll forks sleep:
    # costly under pure emulation, where an idle guest polling at 50 ms kept half a host core busy)
    if [ "$idle" -lt {BUSY_POLLS} ]; then sleep 0.05; else sleep 1; fi
done
sync
{shutdown}
"""
