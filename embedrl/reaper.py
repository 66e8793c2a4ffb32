"""Process groups that end with this process, however it ends.

A machine started in a session of its own (User-Mode Linux forks a host process per guest process; a QEMU
guest) outlives its parent's SIGKILL: no cleanup code of the parent runs, and the guest keeps its cores busy
until someone finds it. :class:`GroupReaper` starts a guardian shell that blocks reading a pipe whose only
write end this process holds. When this process ends, however it ends, the kernel closes that end; the
guardian's ``read`` sees end of file and it kills the group. A normal stop writes :data:`RELEASED` first,
and the guardian exits without killing anything.
"""

from __future__ import annotations

import contextlib
import os
import subprocess

RELEASED = "released"
"""The line that tells the guardian the group was stopped by its owner."""

RELEASE_TIMEOUT_S = 5.0
"""How long a released guardian may take to exit."""


class GroupReaper:
    """Kills process group ``pgid`` with SIGKILL when this process ends without calling :meth:`release`.

    The pipe's write end is close-on-exec, so programs this process starts later do not hold it open; a
    child made by ``fork`` without ``exec`` does, and the group then ends when that child ends too.
    """

    def __init__(self, pgid: int) -> None:
        read_end, self._write_end = os.pipe()
        # dash (Debian's sh) takes neither `-s KILL` nor `--` before a negative process group ID
        script = f'read line; [ "$line" = {RELEASED} ] || kill -9 -{pgid} 2>/dev/null'
        try:
            self._guardian: subprocess.Popen[bytes] | None = subprocess.Popen(
                ["sh", "-c", script],
                stdin=read_end,
                stdout=subprocess.DEVNULL,
                stderr=subprocess.DEVNULL,
                start_new_session=True,  # a Ctrl-C to the terminal's group must not end the guardian first
            )
        finally:
            os.close(read_end)

    def release(self) -> None:
        """The group is stopped: end the guardian without a kill. Idempotent."""
        if self._guardian is None:
            return
        with contextlib.suppress(OSError):
            os.write(self._write_end, f"{RELEASED}\n".encode())
        os.close(self._write_end)
        try:
            self._guardian.wait(timeout=RELEASE_TIMEOUT_S)
        except subprocess.TimeoutExpired:
            self._guardian.kill()
            self._guardian.wait()
        self._guardian = None
