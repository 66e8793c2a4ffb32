"""A virtual-machine guest's job queue, on this machine: the guest's script (``guest.sh``: its job server,
its shell loop) runs here instead of inside a VM, so the protocol between host and guest (shell and Python
jobs, statuses, the shell loop taking over when the server ends) is checked in seconds. The same code runs
in the UML and QEMU guests (tests/hil/test_sandbox_providers.py, test_paths_matrix.py)."""

from __future__ import annotations

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
    booted = VmGuest("local", "local shell", ["sh", str(work / "guest.sh")], work, "", "true", 30.0)
    try:
        yield booted
    finally:
        booted.close()


def python_job(guest: VmGuest, *args: str, cwd: Path = ROOT) -> base.JobResult:
    return guest.run([sys.executable, "-m", JOB, *args], cwd, TIMEOUT_S)


def shell_job(guest: VmGuest, *args: str, cwd: Path = ROOT) -> base.JobResult:
    """The same program through the shell loop (``sh -c``: not a Python job, so not the server's)."""
    return guest.run(["sh", "-c", f'exec "{sys.executable}" -m {JOB} "$@"', "job", *args], cwd, TIMEOUT_S)


def test_a_python_job_runs_in_the_server_as_python_m_runs_it(guest: VmGuest, tmp_path: Path) -> None:
    here = tmp_path / "a job's folder"
    here.mkdir()
    served = [python_job(guest, "exit", "3", cwd=here), python_job(guest, "exit", "0", "two words")]
    direct = [shell_job(guest, "exit", "3", cwd=here), shell_job(guest, "exit", "0", "two words")]
    assert [(r.status, _same(r.output)) for r in served] == [(r.status, _same(r.output)) for r in direct]
    assert all("preloaded=True" in r.output for r in served) and "preloaded=False" in direct[0].output
    assert served[0].status == 3 and f"cwd={here} path0={here}" in served[0].output
    assert "name=__main__ argv=['exit', '0', 'two words']" in served[1].output
    assert "unbuffered=1" in served[1].output
    server = _server(guest)
    assert server is not None
    assert python_job(guest, "exit", "0").status == 0 and _server(guest) == server  # one server throughout


def _same(output: str) -> str:
    """The output without the line that says whether the job found its imports made."""
    return "".join(line for line in output.splitlines(keepends=True) if not line.startswith("preloaded="))


def _server(guest: VmGuest) -> int | None:
    """The pid of the guest's job server, or None."""
    for proc in Path("/proc").iterdir():
        if proc.name.isdigit():
            try:
                cmdline = (proc / "cmdline").read_bytes().split(b"\0")
            except OSError:
                continue
            if b"embedrl.hil.sandbox.job_server" in cmdline and str(guest.queue).encode() in cmdline:
                return int(proc.name)
    return None


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
    served, direct = python_job(guest, "exit", "0", cwd=gone), shell_job(guest, "exit", "0", cwd=gone)
    assert served.status == direct.status == 125


def test_when_the_server_ends_early_the_guests_shell_loop_runs_the_jobs(guest: VmGuest) -> None:
    assert python_job(guest, "exit", "0").status == 0
    with pytest.raises(SandboxError, match="job server ended \\(exited with status 137\\) while running"):
        python_job(guest, "kill-parent")  # the server is the job's parent
    assert "exited with status 137" in (guest.queue / base.SERVER_FAILED).read_text()
    assert shell_job(guest, "exit", "5").status == 5
    result = python_job(guest, "exit", "6")  # a new interpreter, from the shell loop
    assert result.status == 6 and "preloaded=False" in result.output
    assert _server(guest) is None and not list(guest.queue.glob(f"*{base.PYTHON_JOB}"))


def test_should_the_imports_fail_a_python_job_runs_in_a_new_interpreter(
    tmp_path: Path, monkeypatch: pytest.MonkeyPatch
) -> None:
    monkeypatch.setattr(base, "SERVER_PRELOAD", (JOB, "tests.hil.no_such_module"))
    monkeypatch.setenv("PYTHONPATH", str(ROOT))
    booted = VmGuest("local", "local shell", ["sh", str(tmp_path / "guest.sh")], tmp_path, "", "true", 30.0)
    try:
        results = [python_job(booted, "exit", "7"), python_job(booted, "raise")]
        assert [r.status for r in results] == [7, 1] and "preloaded=False" in results[0].output
        assert "ValueError: raised by the job" in results[1].output
        assert (
            "No module named 'tests.hil.no_such_module'" in (tmp_path / "queue" / base.SERVER_LOG).read_text()
        )
        assert _server(booted) is not None  # the server goes on
    finally:
        booted.close()


def test_a_guest_stops_when_asked_with_its_server_idle(guest: VmGuest) -> None:
    assert python_job(guest, "exit", "0").status == 0 and _server(guest) is not None
    guest.close()
    assert guest.process.returncode == 0 and _server(guest) is None
    assert not (guest.queue / base.SERVER_FAILED).exists()
