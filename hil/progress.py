"""A bar of a HIL session's episodes, drawn on the host while the session runs (in a guest or here).

The session rewrites a small file after each episode (:attr:`embedrl.hil.session.SessionConfig.progress`);
a thread here reads it every :data:`POLL_S` and moves the bar. Nothing is drawn when stderr is not a
terminal (a log or a test).
"""

from __future__ import annotations

import threading
from collections.abc import Iterator
from contextlib import contextmanager
from pathlib import Path

from embedrl.common import on_terminal

POLL_S = 0.5
"""How often the file is read."""


@contextmanager
def episode_bar(path: Path, total: int, desc: str = "HIL episodes") -> Iterator[None]:
    """While the block runs, a bar of the episodes ``path`` says are done (of ``total``)."""
    if not on_terminal():
        yield
        return
    from tqdm import tqdm

    stop = threading.Event()
    bar = tqdm(total=total, desc=desc, unit="ep")

    def watch() -> None:
        while not stop.wait(POLL_S):
            bar.update(max(0, read_done(path) - bar.n))

    thread = threading.Thread(target=watch, daemon=True)
    thread.start()
    try:
        yield
    finally:
        stop.set()
        thread.join()
        bar.update(max(0, read_done(path) - bar.n))
        bar.close()


def read_done(path: Path) -> int:
    """Episodes done according to the session's file (0 before the first, or if unreadable)."""
    try:
        return int(path.read_text().split()[0])
    except (OSError, ValueError, IndexError):
        return 0
