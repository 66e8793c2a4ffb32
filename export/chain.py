"""The traceability chain of an export: which run, model, ONNX, C and binaries made it, and which reports
were made on exactly these bytes, each link hashed (``chain.json`` in the export folder).

The links, in order: the run's configuration and seed -> the model (and its normalisation statistics)
-> the ONNX -> the interface -> the generated C -> each binary (the host library the verification ran,
each target's firmware test image and firmware node) -> the verification report -> each HIL report made
on the export afterwards (``embedrl hil run --json`` appends its own). Each link names the links it was
made from; where a file records its parent's hash itself (the C's header names the ONNX's, the ONNX's
metadata the model's, a shipped policy's record the model's, a HIL report the export's files), the check
reads that too.

:func:`verify` recomputes every hash and names the first link that no longer matches.
"""

from __future__ import annotations

import contextlib
import fcntl
import json
import os
import re
import secrets
from collections.abc import Iterator
from dataclasses import asdict, dataclass, field
from pathlib import Path
from typing import Any

from embedrl.common import read_json, sha256
from embedrl.export.errors import ExportError

MANIFEST = "chain.json"
FORMAT = 1


class ChainError(ExportError):
    """No readable manifest in the folder."""


@dataclass(frozen=True)
class Link:
    name: str
    path: str
    """Relative to the export folder when inside it, else absolute."""
    sha256: str
    made_from: list[str] = field(default_factory=list)
    facts: dict[str, Any] = field(default_factory=dict)
    """What the link states about itself (a run's seed, a report's verdict)."""


@dataclass(frozen=True)
class Check:
    link: Link
    ok: bool
    detail: str


def run_config_of(source: Path) -> Path | None:
    """The configuration a model was trained with: a shipped policy's record beside it (``td3.json`` for
    ``td3.zip``) or the run folder's ``config.json`` (the model's folder or its parent's)."""
    candidates = [
        source.with_suffix(".json"),
        source.parent / "config.json",
        source.parent.parent / "config.json",
    ]
    return next((c for c in candidates if c.is_file() and c != source), None)


def seed_of(config: Path) -> int | None:
    """The training seed a run configuration records (a shipped record nests it under ``config``)."""
    try:
        data = read_json(config)
    except (ValueError, OSError):
        return None
    inner = data.get("config", data) if isinstance(data, dict) else None
    seed = inner.get("seed") if isinstance(inner, dict) else None
    return seed if isinstance(seed, int) else None


def link(export_dir: Path, name: str, path: Path, made_from: list[str], **facts: Any) -> Link:
    """A link to ``path`` as it is now."""
    path = path.resolve()
    root = export_dir.resolve()
    shown = str(path.relative_to(root)) if path.is_relative_to(root) else str(path)
    return Link(name, shown, sha256(path), made_from, facts)


def write(export_dir: Path, links: list[Link]) -> Path:
    """Write the manifest atomically: a reader sees the old one or the new one, never a part of either."""
    manifest = export_dir / MANIFEST
    data = {"format": FORMAT, "links": [asdict(k) for k in links]}
    partial = export_dir / f".{MANIFEST}.{secrets.token_hex(6)}.partial"  # one per writer
    try:
        fd = os.open(partial, os.O_WRONLY | os.O_CREAT | os.O_EXCL, 0o666)  # the user's umask applies
        with os.fdopen(fd, "w") as f:
            f.write(json.dumps(data, indent=2) + "\n")
        os.replace(partial, manifest)
    finally:
        partial.unlink(missing_ok=True)
    return manifest


def read(export_dir: Path) -> list[Link]:
    manifest = export_dir / MANIFEST
    if not export_dir.is_dir():
        raise ChainError(f"{export_dir}: no such folder")
    if not manifest.is_file():
        raise ChainError(f"{export_dir}: no {MANIFEST} (export it again with `embedrl export`)")
    try:
        data = read_json(manifest)
        if data.get("format") != FORMAT:
            raise ValueError(f"format {data.get('format')!r}, expected {FORMAT}")
        links = [_link_of(entry) for entry in data["links"]]
        if not links:
            raise ValueError("no links")
        return links
    except (ValueError, TypeError, KeyError, AttributeError) as exc:
        raise ChainError(f"{manifest}: not a chain manifest ({exc})") from None


_DIGEST = re.compile(r"[0-9a-f]{64}")


def _link_of(entry: Any) -> Link:
    """One entry of the manifest, each field of its type (the manifest is a file anyone can edit)."""
    k = Link(**entry)  # a field missing or unknown: TypeError
    if not isinstance(k.name, str) or not k.name:
        raise ValueError(f"a link's name is {k.name!r}, not a text")
    if not isinstance(k.path, str) or not k.path:
        raise ValueError(f"link {k.name!r}: path {k.path!r} is not a file's path")
    if not isinstance(k.sha256, str) or not _DIGEST.fullmatch(k.sha256):
        raise ValueError(f"link {k.name!r}: sha256 {k.sha256!r} is not a SHA-256 digest (64 hex digits)")
    if not isinstance(k.made_from, list) or not all(isinstance(m, str) for m in k.made_from):
        raise ValueError(f"link {k.name!r}: made_from {k.made_from!r} is not a list of link names")
    if not isinstance(k.facts, dict):
        raise ValueError(f"link {k.name!r}: facts {k.facts!r} is not an object")
    return k


def append(export_dir: Path, new: Link) -> None:
    """Add (or replace, by name) a link made on the export later, such as a HIL report. Appends from
    several processes at once each keep their link: each reads, changes and replaces the manifest while
    it holds the manifest's lock."""
    with _locked(export_dir):
        links = [k for k in read(export_dir) if k.name != new.name]
        write(export_dir, [*links, new])


def check_appendable(export_dir: Path) -> None:
    """Refuse, before any work, an export whose manifest could not take a link at the end: ChainError."""
    if not os.access(export_dir, os.W_OK | os.X_OK):
        raise ChainError(f"{export_dir}: the folder is not writable (its {MANIFEST} takes the report's link)")


@contextlib.contextmanager
def _locked(export_dir: Path) -> Iterator[None]:
    """Hold an exclusive lock on the manifest. A writer replaces the file, so a waiter that locked the
    file it opened checks that it still is the one on disk, and otherwise locks the new one."""
    manifest = export_dir / MANIFEST
    while True:
        try:
            fd = os.open(manifest, os.O_RDONLY)
        except FileNotFoundError:
            raise ChainError(f"{export_dir}: no {MANIFEST} (export it again with `embedrl export`)") from None
        fcntl.flock(fd, fcntl.LOCK_EX)
        try:
            current = os.stat(manifest).st_ino == os.fstat(fd).st_ino
        except FileNotFoundError:
            current = False
        if current:
            break
        os.close(fd)
    try:
        yield
    finally:
        os.close(fd)  # releases the lock


def verify(export_dir: Path) -> list[Check]:
    """Every link in order: its file's hash now against the manifest, then what it records of its parents."""
    links = read(export_dir)
    by_name = {k.name: k for k in links} | {f"file {k.path}": k for k in links}
    return [_check(export_dir, k, by_name) for k in links]


def _check(export_dir: Path, k: Link, by_name: dict[str, Link]) -> Check:
    path = Path(k.path) if Path(k.path).is_absolute() else export_dir / k.path
    if not path.is_file():
        return Check(k, False, f"{k.path} is missing")
    now = sha256(path)
    if now != k.sha256:
        return Check(k, False, f"{k.path} changed: sha256 {now[:12]}..., the chain says {k.sha256[:12]}...")
    try:
        parents = _recorded_parents(path, k)
    except ValueError as exc:
        return Check(k, False, f"{k.path}: cannot read the hashes it records of its parents ({exc})")
    for parent, recorded in parents.items():
        if parent in by_name and by_name[parent].sha256 != recorded:
            said = (
                f"records another {parent.removeprefix('file ')} (sha256 {recorded[:12]}...) than the chain's"
                if parent.startswith("file ")
                else f"was made from another {parent} (sha256 {recorded[:12]}...)"
            )
            return Check(k, False, f"{k.path} {said}")
    return Check(k, True, f"{k.path} sha256 {now[:12]}...")


_C_HEADER = re.compile(r"^ \* (source|onnx): (?:\S+ )?sha256 ([0-9a-f]{64})$", re.M)


def _recorded_parents(path: Path, k: Link) -> dict[str, str]:
    """The hashes of its parents that a file records itself, by link name."""
    if path.suffix == ".c" and k.name.startswith("C source"):
        found = dict(_C_HEADER.findall(path.read_text(errors="replace")[:2000]))
        return {name: found[key] for key, name in (("onnx", "ONNX"), ("source", "model")) if key in found}
    if k.name == "run config" and path.suffix == ".json":
        data = read_json(path)
        recorded = data.get("sha256") if isinstance(data, dict) else None
        return {"model": recorded} if isinstance(recorded, str) else {}
    if k.name in ("verification report",) or k.name.startswith("HIL report"):
        # Every export file a report records, against the chain's link of the same path ("file PATH").
        data = read_json(path)
        key = "files" if k.name == "verification report" else "export_files"
        files = (data.get(key) or {}) if isinstance(data, dict) else None
        if not isinstance(files, dict) or not all(isinstance(h, str) for h in files.values()):
            raise ValueError(f"its {key} is not an object of file names and hashes")
        return {f"file {f}": h for f, h in files.items()}
    return {}
