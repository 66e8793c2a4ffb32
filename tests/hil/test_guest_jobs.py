"""A virtual-machine guest's job queue, on this machine: the guest's own loop (``guest.sh``) runs as a local
shell instead of inside a VM, so the protocol between host and guest (shell jobs, the Python job server,
statuses, the fallback when the server fails) is checked in seconds. The same code runs in the UML and QEMU
guests (tests/hil/test_sandbox_providers.py, test_paths_matrix.py)."""

from __future__ import annotations

import os
import sys
from collections.abc import Iterator
from pathlib import Path

import pytest

from embedrl.hil.sandbox import base
from embedrl.hil.sandbox.base import SandboxError, VmGuest

ROOT = Path(__file__).resolve().parents[2]
JOB = "tests.hil.guest_job"
TIMEOUT_S = 120.0


@pytest.fixture
def guest(tmp_path: Path, monkeypatch: pytest.MonkeyPatch) -> Iterator[VmGuest]:
    """A guest whose loop runs here; ``tests.hil.guest_job`` is one of the server's programs."""
    monkeypatch.setattr(base, "SERVER_PRELOAD", (*base.SERVER_PRELOAD, JOB))
    monkeypatch.setenv("PYTHONPATH", str(ROOT))  # tests.hil.guest_job from any folder, as embedrl is
    work = tmp_path / "guest folder"  # a space: every path in the protocol is quoted
    work.mkdir()
    with VmGuest("local", "local shell", ["sh", str(work / "guest.sh")], work, "", "true", 30.0) as booted:
        yield booted


def python_job(guest: VmGuest, *args: str, cwd: Path = ROOT) -> base.JobResult:
    return guest.run([sys.executable, "-m", JOB, *args], cwd, TIMEOUT_S)


def shell_job(guest: VmGuest, *args: str, cwd: Path = ROOT) -> base.JobResult:
    """The same program through the shell loop (``sh -c``: not a Python job, so not the server's)."""
    return guest.run(["sh", "-c", f'exec "{sys.executable}" -m {JOB} "$@"', "job", *args], cwd, TIMEOUT_S)


def test_a_python_job_runs_in_the_server_as_python_m_runs_it(guest: VmGuest, tmp_path: Path) -> None:
    here = tmp_path / "a job's folder"
    here.mkdir()
    served = [python_job(guest, "exit", "3", cwd=here), python_job(guest, "exit", "0", "two words")]
    assert (guest.queue / base.SERVER_READY).is_file() and not list(guest.queue.glob("*.sh"))
    direct = [shell_job(guest, "exit", "3", cwd=here), shell_job(guest, "exit", "0", "two words")]
    assert [(r.status, r.output) for r in served] == [(r.status, r.output) for r in direct]
    assert served[0].status == 3 and f"cwd={here} path0={here}" in served[0].output
    assert "name=__main__ argv=['exit', '0', 'two words']" in served[1].output
    assert "unbuffered=1" in served[1].output
    server_pid = int((guest.queue / base.SERVER_READY).read_text())
    assert python_job(guest, "exit", "0").status == 0 and os.path.exists(f"/proc/{server_pid}")  # one server


@pytest.mark.parametrize(
    ("how", "status", "said"),
    [
        (["raise"], 1, "ValueError: raised by the job"),
        (["kill"], 128 + 9, "name=__main__"),
    ],
)
def test_a_failing_python_job_ends_with_the_status_python_m_gives(
    guest: VmGuest, how: list[str], status: int, said: str
) -> None:
    served, direct = python_job(guest, *how), shell_job(guest, *how)
    assert served.status == direct.status == status
    assert said in served.output and said in direct.output


def test_a_job_whose_folder_is_gone_ends_with_125_on_either_route(guest: VmGuest, tmp_path: Path) -> None:
    gone = tmp_path / "gone"
    assert (
        python_job(guest, "exit", "0", cwd=gone).status
        == shell_job(guest, "exit", "0", cwd=gone).status
        == 125
    )


def test_without_the_server_a_python_job_runs_in_the_shell(guest: VmGuest) -> None:
    (guest.queue / base.SERVER_FAILED).write_text("could not import\n")
    result = python_job(guest, "exit", "4")
    assert result.status == 4 and "name=__main__" in result.output
    assert not (guest.queue / base.SERVER_READY).exists()  # never started


def test_a_server_that_dies_during_a_job_is_an_error_that_says_so(guest: VmGuest) -> None:
    assert python_job(guest, "exit", "0").status == 0
    with pytest.raises(SandboxError, match="Python job server ended \\(exited with status 137\\)"):
        python_job(guest, "kill-parent")
    assert shell_job(guest, "exit", "5").status == 5  # the guest goes on
    assert python_job(guest, "exit", "6").status == 6  # in the shell now
