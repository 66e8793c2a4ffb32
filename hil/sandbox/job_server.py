"""The guest's job server: runs the jobs the host queues (:mod:`embedrl.hil.sandbox.base`), one after
another, until the host asks it to stop.

A shell job (``job-N.sh``) runs in ``sh``. A Python job (``job-N.py.json``: ``python -m MODULE ARGS`` for
one of :data:`~embedrl.hil.sandbox.base.SERVER_PRELOAD`'s programs, which the command line names) runs in a
fork of this server, which imports those programs' dependencies once, at the first such job: a guest under
pure emulation runs Python about ten times slower than the host, and importing numpy, gymnasium,
python-can, cantools and the simulator took ~32 s of every job. A Python job runs as ``python -m`` would
run it: the module as ``__main__`` (``runpy``), its arguments in ``sys.argv``, its folder first on
``sys.path``, its environment; should the imports fail, every Python job runs in a new interpreter instead.
Either kind leaves its output in ``job-N.out`` and its exit status in ``job-N.rc`` (128 + N for a job ended
by signal N, as ``sh`` reports it). The server polls the queue as the shell loop it replaces did, and never
forks to do so.

Run as ``python -m embedrl.hil.sandbox.job_server QUEUE MODULE...`` (the programs whose imports it makes) by
the guest's script, which falls back to its own shell loop should the server end before the host asks it
to stop.
"""

from __future__ import annotations

import json
import os
import runpy
import subprocess
import sys
import time
import traceback
from pathlib import Path
from typing import Any

from embedrl.hil.sandbox.base import BUSY_POLLS, PYTHON_JOB, SHELL_JOB

BUSY_POLL_S = 0.05
IDLE_POLL_S = 1.0
CWD_MISSING = 125
"""A job whose folder is missing ends with this status, as a shell job's ``cd DIR || exit 125``."""


class _Preload:
    """The programs whose imports the server makes, and whether they are done (None: not tried yet)."""

    modules: tuple[str, ...] = ()
    done: bool | None = None


def _status(wait_status: int) -> int:
    code = os.waitstatus_to_exitcode(wait_status)
    return code if code >= 0 else 128 - code


def _finish(base: str, status: int) -> None:
    Path(f"{base}.rc.tmp").write_text(f"{status}\n")
    os.rename(f"{base}.rc.tmp", f"{base}.rc")


def _shell_job(path: Path) -> None:
    base = str(path)[: -len(SHELL_JOB)]
    with open(f"{base}.out", "wb") as out:
        returned = subprocess.run(["sh", str(path)], stdin=subprocess.DEVNULL, stdout=out, stderr=out)
    _finish(base, returned.returncode if returned.returncode >= 0 else 128 - returned.returncode)
    path.unlink()


def _python_job(path: Path) -> None:
    base = str(path)[: -len(PYTHON_JOB)]
    job = json.loads(path.read_text())
    path.unlink()
    if _Preload.done is None:
        try:
            for module in _Preload.modules:
                __import__(module)
            _Preload.done = True
        except Exception:  # the jobs then run in new interpreters, which report the error themselves
            traceback.print_exc()
            _Preload.done = False
    sys.stdout.flush()
    sys.stderr.flush()
    pid = os.fork()
    if pid == 0:
        status = 1
        try:
            out = os.open(f"{base}.out", os.O_WRONLY | os.O_CREAT | os.O_TRUNC, 0o644)
            os.dup2(out, 1)
            os.dup2(out, 2)
            os.close(out)
            sys.stdout.reconfigure(line_buffering=True)  # type: ignore[union-attr]
            status = _run(job) if _Preload.done else _exec(job)
        finally:
            sys.stdout.flush()
            sys.stderr.flush()
            os._exit(status & 0xFF)
    _finish(base, _status(os.waitpid(pid, 0)[1]))


def _enter(job: dict[str, Any]) -> bool:
    os.environ.update(job["env"])
    try:
        os.chdir(str(job["cwd"]))
    except OSError as exc:
        print(f"cannot enter {job['cwd']}: {exc}", file=sys.stderr)
        return False
    return True


def _exec(job: dict[str, Any]) -> int:
    """In the fork, without the imports: the job in a new interpreter."""
    if not _enter(job):
        return CWD_MISSING
    os.execv(sys.executable, [sys.executable, "-m", str(job["module"]), *job["args"]])


def _run(job: dict[str, Any]) -> int:
    """In the fork: the job as ``python -m`` runs it; its exit status."""
    if not _enter(job):
        return CWD_MISSING
    module = str(job["module"])
    sys.argv = [module, *job["args"]]
    sys.path[0] = os.getcwd()  # the server's own folder until now (it was started with -m)
    sys.modules.pop(module, None)  # imported as a dependency: run a fresh copy as __main__, as -m does
    try:
        runpy.run_module(module, run_name="__main__", alter_sys=True)
    except SystemExit as exc:
        if exc.code is None or isinstance(exc.code, int):
            return exc.code or 0
        print(exc.code, file=sys.stderr)
        return 1
    except BaseException:  # as the interpreter reports an uncaught exception
        traceback.print_exc()
        return 1
    return 0


def _number(path: Path) -> int:
    return int(path.name.split(".", 1)[0].removeprefix("job-"))


def serve(queue: Path) -> None:
    """Run the queue's jobs in order until ``queue/stop`` appears: every 50 ms while jobs come; once idle
    for BUSY_POLLS polls, every second."""
    idle = 0
    while not (queue / "stop").exists():
        idle += 1
        jobs = [*queue.glob(f"job-*{SHELL_JOB}"), *queue.glob(f"job-*{PYTHON_JOB}")]
        for path in sorted(jobs, key=_number):
            (_shell_job if path.name.endswith(SHELL_JOB) else _python_job)(path)
            idle = 0
        time.sleep(BUSY_POLL_S if idle < BUSY_POLLS else IDLE_POLL_S)


if __name__ == "__main__":
    _Preload.modules = tuple(sys.argv[2:])
    serve(Path(sys.argv[1]))
