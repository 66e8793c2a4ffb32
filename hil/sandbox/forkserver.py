"""The guest's Python job server: imports the HIL programs' dependencies once, then runs each Python job
the host queues (``python -m MODULE ARGS``) in a fork of itself.

A guest under pure emulation runs Python about ten times slower than the host: importing numpy,
gymnasium, python-can, cantools and the simulator took ~32 s of every job. The server pays that once per
guest; a job then starts in a fork that has them all. A job runs as ``python -m`` would run it: the module
as ``__main__`` (``runpy``), its arguments in ``sys.argv``, the job's folder first on ``sys.path``, its
environment, its output and exit status in the queue like a shell job's (:mod:`embedrl.hil.sandbox.base`).

Run as ``python -m embedrl.hil.sandbox.forkserver QUEUE`` inside the guest (the host starts it, in the
background, with the first job it can take); it writes ``QUEUE/forkserver`` once it is ready (or
``QUEUE/forkserver.failed`` with the reason), and ends when ``QUEUE/stop`` appears.
"""

from __future__ import annotations

import json
import os
import runpy
import sys
import time
import traceback
from pathlib import Path

from embedrl.hil.sandbox.base import (
    BUSY_POLLS,
    PYTHON_JOB,
    SERVER_FAILED,
    SERVER_PRELOAD,
    SERVER_READY,
)

BUSY_POLL_S = 0.05
IDLE_POLL_S = 1.0
CWD_MISSING = 125
"""A job whose folder is missing ends with this status, as a shell job's ``cd DIR || exit 125``."""


def _run_job(job: dict[str, object]) -> int:
    """In the fork: the job as ``python -m`` runs it; its exit status."""
    os.environ.update(job["env"])  # type: ignore[arg-type]
    try:
        os.chdir(str(job["cwd"]))
    except OSError as exc:
        print(f"cannot enter {job['cwd']}: {exc}", file=sys.stderr)
        return CWD_MISSING
    module = str(job["module"])
    sys.argv = [module, *job["args"]]  # type: ignore[misc]
    sys.path[0] = os.getcwd()  # the server's own folder until now (it was started with -m)
    sys.modules.pop(module, None)  # preloaded as a dependency: run a fresh copy as __main__, as -m does
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


def _fork_job(path: Path) -> None:
    """Run the job of ``path`` in a fork; its output and status beside it."""
    base = str(path)[: -len(PYTHON_JOB)]
    job = json.loads(path.read_text())
    path.unlink()
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
            status = _run_job(job)
        finally:
            sys.stdout.flush()
            sys.stderr.flush()
            os._exit(status & 0xFF)
    _, wait_status = os.waitpid(pid, 0)
    status = os.waitstatus_to_exitcode(wait_status)
    Path(f"{base}.rc.tmp").write_text(f"{status if status >= 0 else 128 - status}\n")
    os.rename(f"{base}.rc.tmp", f"{base}.rc")


def serve(queue: Path) -> None:
    """Run the queue's Python jobs, one after another, until ``queue/stop`` appears."""
    idle = 0
    while not (queue / "stop").exists():
        idle += 1
        for path in sorted(queue.glob(f"job-*{PYTHON_JOB}")):
            _fork_job(path)
            idle = 0
        time.sleep(BUSY_POLL_S if idle < BUSY_POLLS else IDLE_POLL_S)


def main(queue: Path) -> int:
    try:
        for module in SERVER_PRELOAD:
            __import__(module)
    except BaseException as exc:  # the guest's shell runs every job instead
        (queue / SERVER_FAILED).write_text(f"{type(exc).__name__}: {exc}\n")
        return 1
    (queue / SERVER_READY).write_text(f"{os.getpid()}\n")
    serve(queue)
    return 0


if __name__ == "__main__":
    sys.exit(main(Path(sys.argv[1])))
