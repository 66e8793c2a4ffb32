"""A program for the guest job tests (tests/hil/test_guest_jobs.py): ``python -m tests.hil.guest_job HOW
[ARGS...]`` prints what a job sees, then ends as ``HOW`` says: ``exit N``, ``raise``, ``kill`` (SIGKILL to
itself) or ``kill-parent`` (SIGKILL to the process that started it, then exit 0)."""

from __future__ import annotations

import os
import signal
import sys

if __name__ == "__main__":
    how, *rest = sys.argv[1:]
    print(f"name={__name__} argv={sys.argv[1:]} cwd={os.getcwd()} path0={sys.path[0]}")
    print(f"unbuffered={os.environ.get('PYTHONUNBUFFERED')}", file=sys.stderr)
    print(f"preloaded={'embedrl.hil.session' in sys.modules}")  # imported before the job started
    if how == "exit":
        sys.exit(int(rest[0]))
    if how == "raise":
        raise ValueError("raised by the job")
    if how == "kill":
        os.kill(os.getpid(), signal.SIGKILL)
    if how == "kill-parent":
        os.kill(os.getppid(), signal.SIGKILL)
