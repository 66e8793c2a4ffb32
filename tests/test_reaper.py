"""A process group guarded by :class:`GroupReaper` ends with its owner, even when the owner is SIGKILLed,
and survives an owner that released it."""

from __future__ import annotations

import os
import signal
import subprocess
import sys
import time
from pathlib import Path

OWNER = """
import subprocess, sys, time
from embedrl.reaper import GroupReaper
group = subprocess.Popen(["sh", "-c", "sleep 600 & sleep 600"], start_new_session=True)
reaper = GroupReaper(group.pid)
if sys.argv[1] == "release":
    reaper.release()
print(group.pid, flush=True)
time.sleep(600)
"""
"""A process that starts a group of two sleeps, guards it, and waits to be killed."""

DEADLINE_S = 30.0
"""How long the group may take to end after its owner (generous: the machine may be loaded)."""


def group_alive(pgid: int) -> bool:
    try:
        os.killpg(pgid, 0)
    except ProcessLookupError:
        return False
    return True


def ended_within_deadline(pgid: int) -> bool:
    """Whether process group ``pgid`` ends within :data:`DEADLINE_S`; one that does not is killed."""
    deadline = time.monotonic() + DEADLINE_S
    while group_alive(pgid) and time.monotonic() < deadline:
        time.sleep(0.05)
    alive = group_alive(pgid)
    if alive:
        os.killpg(pgid, signal.SIGKILL)
    return not alive


def start_owner(mode: str, tmp_path: Path) -> tuple[subprocess.Popen[str], int]:
    script = tmp_path / "owner.py"
    script.write_text(OWNER)
    owner = subprocess.Popen([sys.executable, str(script), mode], stdout=subprocess.PIPE, text=True)
    assert owner.stdout is not None
    pgid = int(owner.stdout.readline())
    assert group_alive(pgid)
    return owner, pgid


def test_a_guarded_group_ends_when_its_owner_is_killed(tmp_path: Path) -> None:
    owner, pgid = start_owner("guard", tmp_path)
    owner.send_signal(signal.SIGKILL)
    owner.wait()
    assert ended_within_deadline(pgid), "the group outlived its killed owner"


def test_a_released_group_is_left_alone(tmp_path: Path) -> None:
    owner, pgid = start_owner("release", tmp_path)
    owner.send_signal(signal.SIGKILL)
    owner.wait()
    time.sleep(1.0)  # a guardian that wrongly fired would have killed the group by now
    try:
        assert group_alive(pgid)
    finally:
        os.killpg(pgid, signal.SIGKILL)
