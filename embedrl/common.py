"""Shared by every package (the bottom layer): atomic files, temporary folders a killed process leaves
are removed by the next, JSON reports with provenance, key-value tables, and the seed bases that keep the
seeds of different purposes apart.
"""

from __future__ import annotations

import contextlib
import fcntl
import hashlib
import json
import math
import os
import shutil
import stat
import subprocess
import sys
import tempfile
from collections.abc import Callable, Iterable, Iterator
from datetime import UTC, datetime
from importlib import metadata
from pathlib import Path
from typing import Any

# Seed bases: an evaluation with seed S resets episode i with S + i, so bases a million apart never
# share a start pose between purposes (training uses seeds 0..999,999).
VALIDATION_SEED = 1_000_000
"""Deterministic evaluations during training (validation: the model kept is chosen on these)."""
BENCH_TEST_SEED = 2_000_000
"""The benchmark's held-out evaluation of every trained model."""
DEMONSTRATION_SEED = 3_000_000
"""Episodes of the potential-field controller put into the replay buffer as demonstrations."""
SHIP_TEST_SEED = 5_000_000
"""The quality gate of shipped policies."""
EXAMPLE_SEED = 900_000
"""Rollouts of the example actor's imitation data."""
ROLLOUT_SEED_OFFSET = 1_000_000
"""The export's verification rollouts start this far above the export's ``--seed``."""

PROVENANCE_PACKAGES = ("embedrl", "gymnasium", "pymunk", "numpy", "stable-baselines3", "torch")


SYSTEM_TOOL_DIRS = ("/usr/local/sbin", "/usr/sbin", "/sbin")
"""Where Debian puts system tools (kmod's ``insmod`` and ``modprobe``, iproute2's ``ip``): a non-root user's
PATH often lacks them although they run for any user."""


def system_tool(name: str) -> str | None:
    """The path of the program ``name``: on PATH, else in :data:`SYSTEM_TOOL_DIRS`; None if in neither."""
    return shutil.which(name) or shutil.which(name, path=os.pathsep.join(SYSTEM_TOOL_DIRS))


def on_terminal() -> bool:
    """Whether progress bars are drawn: only when stderr is a terminal (a log or a pipe gets none)."""
    return sys.stderr.isatty()


def atomic_write(path: Path, write: Callable[[Path], object]) -> None:
    """Call ``write(tmp)`` on a temporary file beside ``path``, then rename it to ``path``.

    Creates missing parent folders. If anything fails, the temporary file is removed and
    ``path`` keeps its previous content (or stays absent).
    """
    path.parent.mkdir(parents=True, exist_ok=True)
    tmp = path.with_name(f".{path.name}.partial")
    try:
        write(tmp)
        os.replace(tmp, path)
    finally:
        tmp.unlink(missing_ok=True)


def process_umask() -> int:
    """The process's umask: read where Linux shows it, otherwise set and restored at once."""
    try:
        for line in Path("/proc/self/status").read_text().splitlines():
            if line.startswith("Umask:"):
                return int(line.split()[1], 8)
    except (OSError, ValueError, IndexError):
        pass
    mask = os.umask(0o022)
    os.umask(mask)
    return mask


def with_umask(folder: Path) -> None:
    """Give a folder that ``tempfile.mkdtemp`` made (mode 0700: private) the mode ``mkdir`` would have
    given it, 0777 less the umask: for a temporary folder that becomes an output."""
    folder.chmod(0o777 & ~process_umask())


OWNER_FILE = ".owner"
"""In a folder made by :func:`owned_temporary_folder`: the file its process holds a lock on."""


@contextlib.contextmanager
def owned_temporary_folder(prefix: str, parent: Path | None = None) -> Iterator[Path]:
    """A temporary folder (``prefix`` + random, in ``parent`` or the temporary folder) removed at the end,
    like ``tempfile.TemporaryDirectory``. Its process holds a lock on a file in it while it is used, so a
    folder left by a killed process (its lock free) is told from a live one: folders of the same prefix
    left that way are removed first."""
    base = Path(parent or tempfile.gettempdir())
    remove_abandoned_folders(base, prefix)
    folder = Path(tempfile.mkdtemp(prefix=prefix, dir=base))
    claim = folder / f"{OWNER_FILE}.new"
    fd = os.open(claim, os.O_CREAT | os.O_RDWR, 0o600)
    try:
        fcntl.flock(fd, fcntl.LOCK_EX)
        os.rename(claim, folder / OWNER_FILE)  # seen by others only once locked
        yield folder
    finally:
        shutil.rmtree(folder, ignore_errors=True)
        os.close(fd)


def remove_abandoned_folders(base: Path, prefix: str) -> None:
    """Remove the folders of :func:`owned_temporary_folder` in ``base`` whose name starts with ``prefix``,
    that this user owns and whose process is gone (the lock on their owner file is free)."""
    try:
        candidates = [p for p in base.iterdir() if p.name.startswith(prefix)]
    except OSError:
        return
    for folder in candidates:
        try:
            if folder.is_symlink() or folder.lstat().st_uid != os.getuid():
                continue
            fd = os.open(folder / OWNER_FILE, os.O_RDWR | os.O_NOFOLLOW)
        except OSError:
            continue  # not such a folder (or no longer there)
        try:
            fcntl.flock(fd, fcntl.LOCK_EX | fcntl.LOCK_NB)
        except BlockingIOError:
            os.close(fd)
            continue  # its process is running
        try:
            shutil.rmtree(folder, ignore_errors=True)
        finally:
            os.close(fd)


def sha256(path: Path) -> str:
    """The file's SHA-256 in hex, read in blocks."""
    digest = hashlib.sha256()
    with path.open("rb") as f:
        for block in iter(lambda: f.read(1 << 20), b""):
            digest.update(block)
    return digest.hexdigest()


def parse_json(text: str | bytes) -> Any:
    """``json.loads`` for untrusted text: a document nested too deeply for the parser is a ValueError,
    like any other malformed document, not a RecursionError."""
    try:
        return json.loads(text)
    except RecursionError:
        raise ValueError("JSON nested too deeply") from None


MAX_JSON_BYTES = 16 * 2**20
"""The largest JSON file any command reads (reports, manifests, configurations are far smaller)."""


def read_json(path: Path, limit: int = MAX_JSON_BYTES) -> Any:
    """A JSON file parsed as :func:`parse_json` does, read only if it is a regular file of at most
    ``limit`` bytes: a FIFO (which would block), a device (``/dev/zero`` never ends) or a huge file is a
    ValueError naming ``path``, before anything is read. OSError if it cannot be opened."""
    fd = os.open(path, os.O_RDONLY | os.O_NONBLOCK)  # opening a FIFO does not wait for a writer
    with os.fdopen(fd, "rb") as f:
        info = os.fstat(fd)
        if not stat.S_ISREG(info.st_mode):
            raise ValueError(f"{path}: not a regular file but {_file_kind(info.st_mode)}")
        if info.st_size > limit:
            raise ValueError(f"{path}: {info.st_size:,} bytes exceed the limit of {limit:,} for a JSON file")
        data = f.read(limit + 1)
    if len(data) > limit:  # grew since
        raise ValueError(f"{path}: more than {limit:,} bytes, the limit for a JSON file")
    return parse_json(data)


def _file_kind(mode: int) -> str:
    kinds = {stat.S_ISDIR: "a folder", stat.S_ISFIFO: "a FIFO", stat.S_ISCHR: "a character device",
             stat.S_ISBLK: "a block device", stat.S_ISSOCK: "a socket"}  # fmt: skip
    return next((name for test, name in kinds.items() if test(mode)), "not a file")


def check_output(path: Path, option: str, folder: bool = False) -> None:
    """Refuse, before any work, an output ``path`` that could not be written at the end: ``path`` an
    existing folder (a file is wanted) or file (a folder is wanted), or its nearest existing ancestor
    not a writable folder. Missing folders are left to the writer, so a refused or failed run leaves
    nothing behind. ValueError names ``option``."""
    if folder and path.exists() and not path.is_dir():
        raise ValueError(f"{option} {path}: a file is in the way of the folder")
    if not folder and path.is_dir():
        raise ValueError(f"{option} {path}: is a folder; give a file name")
    ancestor = (path if folder else path.parent).absolute()
    while not ancestor.exists():
        ancestor = ancestor.parent
    if not ancestor.is_dir():
        raise ValueError(f"{option} {path}: {ancestor} is a file, not a folder")
    if not os.access(ancestor, os.W_OK | os.X_OK):
        raise ValueError(f"{option} {path}: {ancestor} is not writable")


def provenance() -> dict[str, Any]:
    """What produced a result: the command line, when (UTC), the versions of the packages that matter and
    the embedrl source's git commit (:func:`source_commit`)."""
    versions: dict[str, str | None] = {}
    for pkg in PROVENANCE_PACKAGES:
        try:
            versions[pkg] = metadata.version(pkg)
        except metadata.PackageNotFoundError:
            versions[pkg] = None
    return {
        "command": sys.argv,
        "date": datetime.now(UTC).isoformat(timespec="seconds"),
        "python": sys.version.split()[0],
        "versions": versions,
        "commit": source_commit(),
    }


def source_commit() -> dict[str, Any] | None:
    """The git commit of the embedrl source that ran (``sha``) and whether tracked files differed from it
    (``modified``); None outside a git checkout (an installed wheel) or without git."""
    root = Path(__file__).resolve().parents[1]
    if not (root / ".git").exists():
        return None
    try:
        sha = subprocess.run(["git", "-C", str(root), "rev-parse", "HEAD"], capture_output=True, text=True)
        status = subprocess.run(
            ["git", "-C", str(root), "status", "--porcelain", "--untracked-files=no"],
            capture_output=True,
            text=True,
        )
    except OSError:
        return None
    if sha.returncode != 0 or status.returncode != 0:
        return None
    return {"sha": sha.stdout.strip(), "modified": bool(status.stdout.strip())}


def write_json(data: dict[str, Any], path: Path) -> None:
    """Write JSON atomically: the file is complete or absent, never half-written. NaN becomes null."""
    text = json.dumps(_finite(data), indent=2, allow_nan=False) + "\n"
    atomic_write(path, lambda tmp: tmp.write_text(text))


def _finite(value: Any) -> Any:
    if isinstance(value, float) and not math.isfinite(value):
        return None
    if isinstance(value, dict):
        return {k: _finite(v) for k, v in value.items()}
    if isinstance(value, list | tuple):
        return [_finite(v) for v in value]
    return value


def table(rows: Iterable[tuple[str, object]]) -> str:
    """Key-value rows, keys padded to one column: the format of every report the CLI prints."""
    pairs = [(k, " ".join(map(str, v)) if isinstance(v, list) else str(v)) for k, v in rows]
    if not pairs:
        return ""
    width = max(len(k) for k, _ in pairs)
    return "\n".join(f"{k:<{width}}  {v}" for k, v in pairs)


def print_measurement(result: dict[str, Any], json_path: Path | None) -> None:
    """A benchmark's numbers as a table; with ``json_path`` also as JSON with provenance."""
    print(table(result.items()))
    if json_path:
        write_json({**result, "provenance": provenance()}, json_path)
        print(f"wrote {json_path}")
