"""The traceability chain of an export: which run, model, ONNX, C and binaries made it, and which reports
were made on exactly these bytes, each link hashed (``chain.json`` in the export folder).

The links, in order: the run's configuration and seed -> the model (and its normalisation statistics)
-> the ONNX -> the interface -> the generated C -> each binary (the host library the verification ran,
each target's firmware test image and firmware node) -> the verification report -> each HIL report made
on the export afterwards (``embedrl hil run --json`` appends its own). Each link names the links it was
made from; where a file records its parent's hash itself (the C's header names the ONNX's, the ONNX's
metadata the model's, a shipped policy's record the model's, a HIL report the export's files), the check
reads that too.

The export folder is a bundle that travels: every path is relative to it. A file that lives outside it
(the source model, its normalisation statistics, a HIL report written elsewhere) is a link by digest only:
its bytes are not in the bundle, so its hash is not recomputed, but the files that record it (the C's
header, the run record) are checked against it. The run configuration is copied into ``provenance/``.

The manifest is an in-toto Statement (https://in-toto.io/Statement/v1): its ``subject`` is every file of
the bundle with its SHA-256, its predicate the links and the steps that made them (each step's tool,
command, inputs and outputs), so supply-chain tools read it as it is. :mod:`embedrl.export.signature`
signs it.

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
from pathlib import Path, PurePosixPath
from typing import Any

from embedrl.common import read_json, sha256
from embedrl.export.errors import ExportError

MANIFEST = "chain.json"
STATEMENT_TYPE = "https://in-toto.io/Statement/v1"
PREDICATE_TYPE = "https://embedrl.dev/traceability-chain/v2"
"""What the predicate holds: ``links`` (this module's :class:`TraceLink`) and ``steps`` (:class:`Step`)."""
OLD_FORMAT = 1
"""The manifest before it was an in-toto Statement: ``{"format": 1, "links": [...]}``, absolute paths for
files outside the export; still read (those links become digest-only) and rewritten as a Statement by
the next append."""
PROVENANCE = "provenance"
"""The bundle's folder for copies of what the export was made from (the run configuration)."""


class ChainError(ExportError):
    """No readable manifest in the folder."""


@dataclass(frozen=True)
class TraceLink:
    """One file of the traceability chain: its hash and the links it was made from."""

    name: str
    path: str
    """Relative to the export folder (``/``-separated); for a link outside it, the file's name only."""
    sha256: str
    made_from: list[str] = field(default_factory=list)
    facts: dict[str, Any] = field(default_factory=dict)
    """What the link states about itself (a run's seed, a report's verdict)."""
    in_bundle: bool = True
    """False for a file outside the export folder: its digest is recorded, its bytes are not there."""


@dataclass(frozen=True)
class Step:
    """One command that made links: its tool, its command line, the links it read and the links it wrote."""

    name: str
    tool: str
    command: list[str]
    inputs: list[str]
    """TraceLink names (:attr:`TraceLink.name`)."""
    outputs: list[str]
    """TraceLink names (:attr:`TraceLink.name`)."""


@dataclass(frozen=True)
class TraceCheck:
    """One link checked against the file it names (``embedrl verify-chain``)."""

    link: TraceLink
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


def link(export_dir: Path, name: str, path: Path, made_from: list[str], **facts: Any) -> TraceLink:
    """A link to ``path`` as it is now: by its path in the bundle, or by digest only if it lies outside."""
    path = path.resolve()
    root = export_dir.resolve()
    if path.is_relative_to(root):
        return TraceLink(name, path.relative_to(root).as_posix(), sha256(path), made_from, facts)
    return TraceLink(name, path.name, sha256(path), made_from, facts, in_bundle=False)


def statement(links: list[TraceLink], steps: list[Step]) -> dict[str, Any]:
    """The manifest's content: an in-toto Statement whose subjects are the bundle's files."""
    by_name = {k.name: k for k in links}

    def descriptor(k: TraceLink) -> dict[str, Any]:
        return {"name": k.path, "digest": {"sha256": k.sha256}, "annotations": {"link": k.name}}

    return {
        "_type": STATEMENT_TYPE,
        "subject": [{"name": k.path, "digest": {"sha256": k.sha256}} for k in links if k.in_bundle],
        "predicateType": PREDICATE_TYPE,
        "predicate": {
            "links": [asdict(k) for k in links],
            "steps": [
                {
                    "name": s.name,
                    "tool": s.tool,
                    "command": s.command,
                    "inputs": [descriptor(by_name[n]) for n in s.inputs if n in by_name],
                    "outputs": [descriptor(by_name[n]) for n in s.outputs if n in by_name],
                }
                for s in steps
            ],
        },
    }


def write(export_dir: Path, links: list[TraceLink], steps: list[Step]) -> Path:
    """Write the manifest atomically: a reader sees the old one or the new one, never a part of either."""
    manifest = export_dir / MANIFEST
    data = statement(links, steps)
    partial = export_dir / f".{MANIFEST}.{secrets.token_hex(6)}.partial"  # one per writer
    try:
        fd = os.open(partial, os.O_WRONLY | os.O_CREAT | os.O_EXCL, 0o666)  # the user's umask applies
        with os.fdopen(fd, "w") as f:
            f.write(json.dumps(data, indent=2) + "\n")
        os.replace(partial, manifest)
    finally:
        partial.unlink(missing_ok=True)
    return manifest


@dataclass(frozen=True)
class Manifest:
    links: list[TraceLink]
    steps: list[Step]
    declared: dict[str, set[str]]
    """Every digest the Statement's subjects and steps give each link (by name): each must be the link's."""


def read(export_dir: Path) -> list[TraceLink]:
    return read_manifest(export_dir).links


def read_manifest(export_dir: Path) -> Manifest:
    manifest = export_dir / MANIFEST
    if not export_dir.is_dir():
        raise ChainError(f"{export_dir}: no such folder")
    if not manifest.is_file():
        raise ChainError(f"{export_dir}: no {MANIFEST} (export it again with `embedrl export`)")
    try:
        data = read_json(manifest)
        if not isinstance(data, dict):
            raise ValueError(f"a {type(data).__name__}, not an object")
        if data.get("format") == OLD_FORMAT:
            links = [_migrated(_link_of(entry, old=True)) for entry in data["links"]]
            result = Manifest(links, [], {})
        else:
            result = _from_statement(data)
        if not result.links:
            raise ValueError("no links")
        names = [k.name for k in result.links]
        if len(set(names)) != len(names):
            raise ValueError("two links of one name")
        return result
    except (ValueError, TypeError, KeyError, AttributeError) as exc:
        raise ChainError(f"{manifest}: not a chain manifest ({exc})") from None


def _from_statement(data: dict[str, Any]) -> Manifest:
    if data.get("_type") != STATEMENT_TYPE or data.get("predicateType") != PREDICATE_TYPE:
        raise ValueError(
            f"_type {data.get('_type')!r} and predicateType {data.get('predicateType')!r}, expected "
            f"{STATEMENT_TYPE} and {PREDICATE_TYPE}"
        )
    predicate = data["predicate"]
    links = [_link_of(entry) for entry in predicate["links"]]
    if not links:
        raise ValueError("no links")
    by_path = {k.path: k.name for k in links if k.in_bundle}
    declared: dict[str, set[str]] = {}
    for subject in data["subject"]:
        name = by_path.get(subject["name"])
        if name is None:
            raise ValueError(f"subject {subject['name']!r} is no link's file")
        declared.setdefault(name, set()).add(_digest_of(subject))
    steps = []
    for entry in predicate["steps"]:
        ends: dict[str, list[str]] = {"inputs": [], "outputs": []}
        for end, names in ends.items():
            for descriptor in entry[end]:
                name = descriptor["annotations"]["link"]
                declared.setdefault(name, set()).add(_digest_of(descriptor))
                names.append(name)
        step = Step(entry["name"], entry["tool"], entry["command"], ends["inputs"], ends["outputs"])
        if not all(isinstance(v, str) for v in (step.name, step.tool, *step.command)):
            raise ValueError(f"step {step.name!r}: its name, tool and command are not texts")
        steps.append(step)
    unknown = sorted(set(declared) - {k.name for k in links})
    if unknown:
        raise ValueError(f"a subject or step names {unknown[0]!r}, which is no link")
    return Manifest(links, steps, declared)


def _digest_of(descriptor: Any) -> str:
    digest = descriptor["digest"]["sha256"]
    if not isinstance(digest, str):
        raise ValueError(f"{descriptor['name']!r}: digest {digest!r} is not a text")
    return digest


def _migrated(k: TraceLink) -> TraceLink:
    """An old manifest's link: an absolute path (a file outside the export folder) becomes digest-only."""
    if not Path(k.path).is_absolute():
        return k
    return TraceLink(k.name, Path(k.path).name, k.sha256, k.made_from, k.facts, in_bundle=False)


_DIGEST = re.compile(r"[0-9a-f]{64}")


def _link_of(entry: Any, old: bool = False) -> TraceLink:
    """One entry of the manifest, each field of its type (the manifest is a file anyone can edit)."""
    if not old and "in_bundle" not in entry:
        raise TypeError("a link without in_bundle")
    k = TraceLink(**entry)  # a field missing or unknown: TypeError
    if not isinstance(k.name, str) or not k.name:
        raise ValueError(f"a link's name is {k.name!r}, not a text")
    if not isinstance(k.path, str) or not k.path:
        raise ValueError(f"link {k.name!r}: path {k.path!r} is not a file's path")
    if not isinstance(k.in_bundle, bool):
        raise ValueError(f"link {k.name!r}: in_bundle {k.in_bundle!r} is not true or false")
    if not old and not inside(k.path):
        raise ValueError(f"link {k.name!r}: path {k.path!r} is not a path inside the export folder")
    if not isinstance(k.sha256, str) or not _DIGEST.fullmatch(k.sha256):
        raise ValueError(f"link {k.name!r}: sha256 {k.sha256!r} is not a SHA-256 digest (64 hex digits)")
    if not isinstance(k.made_from, list) or not all(isinstance(m, str) for m in k.made_from):
        raise ValueError(f"link {k.name!r}: made_from {k.made_from!r} is not a list of link names")
    if not isinstance(k.facts, dict):
        raise ValueError(f"link {k.name!r}: facts {k.facts!r} is not an object")
    return k


def inside(path: str) -> bool:
    """A relative ``/``-separated path that stays inside the folder it is relative to."""
    parts = PurePosixPath(path).parts
    return bool(parts) and not PurePosixPath(path).is_absolute() and ".." not in parts and "\\" not in path


def append(
    export_dir: Path, new: TraceLink, step: Step | None = None, replaces: tuple[str, ...] = ()
) -> None:
    """Add (or replace, by name) a link made on the export later, such as a HIL report, with the step that
    made it; ``replaces`` names links the new one stands for (a digest-only link now in the bundle: the
    steps that named it name the new one). Appends from several processes at once each keep their link:
    each reads, changes and replaces the manifest while it holds the manifest's lock."""
    with _locked(export_dir):
        manifest = read_manifest(export_dir)
        gone = {new.name, *replaces}
        links = [k for k in manifest.links if k.name not in gone]
        steps = [
            Step(s.name, s.tool, s.command, [new.name if n in gone else n for n in s.inputs],
                 [new.name if n in gone else n for n in s.outputs])
            for s in manifest.steps
            if step is None or new.name not in s.outputs
        ]  # fmt: skip
        write(export_dir, [*links, new], [*steps, *([step] if step else [])])


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


def verify(export_dir: Path) -> list[TraceCheck]:
    """Every link in order: what the Statement's subjects and steps say of it, its file's hash now against
    the manifest, then what it records of its parents; then the chain's shape (:func:`layout`): every link
    an export must have, and a link for every file the export made."""
    manifest = read_manifest(export_dir)
    links = manifest.links
    by_name = {k.name: k for k in links} | {f"file {k.path}": k for k in links if k.in_bundle}
    checks = [_check(export_dir, k, by_name, manifest.declared.get(k.name, set())) for k in links]
    return checks + [
        TraceCheck(TraceLink(f"layout: {what}", what, ""), False, why)
        for what, why in layout(export_dir, links)
    ]


REQUIRED_LINKS = ("ONNX", "verification report")
"""Links every export has, whatever its source, precision and targets."""
REQUIRED_KINDS = ("C source ", "binary host/")
"""Link name prefixes of which every export has at least one (the generated C, the host library the
verification ran)."""
PRODUCTS = (
    "policy.onnx",
    "interface.json",
    "export_report.json",
    "c",
    "can",
    "can-fd",
    "test",
    "bin",
    PROVENANCE,
)
"""What ``embedrl export`` writes into its folder (files, and folders whose every file it wrote): each is a
link of the chain, so a file of these that no link covers is one the chain says nothing about."""


def layout(export_dir: Path, links: list[TraceLink]) -> list[tuple[str, str]]:
    """What the chain lacks for the shape of an export (in-toto's layout: the steps' expected materials and
    products), as ``(what, why)``: a required link missing, or a file the export wrote that no link covers."""
    names = {k.name for k in links}
    covered = {k.path for k in links if k.in_bundle}
    problems = [(name, f"the chain has no {name!r} link: every export has one") for name in REQUIRED_LINKS
                if name not in names]  # fmt: skip
    problems += [
        (prefix.strip(), f"the chain has no {prefix.strip()!r} link: every export has one")
        for prefix in REQUIRED_KINDS
        if not any(n.startswith(prefix) for n in names)
    ]
    for product in PRODUCTS:
        root = export_dir / product
        files = (
            [root]
            if root.is_file()
            else sorted(p for p in root.rglob("*") if p.is_file())
            if root.is_dir()
            else []
        )
        for file in files:
            relative = file.relative_to(export_dir).as_posix()
            if relative not in covered:
                problems.append((relative, f"{relative} is in the export but no link of the chain covers it"))
    return problems


def _check(export_dir: Path, k: TraceLink, by_name: dict[str, TraceLink], declared: set[str]) -> TraceCheck:
    other = sorted(declared - {k.sha256})
    if other:
        return TraceCheck(
            k, False, f"{MANIFEST} gives {k.path} two digests: {other[0][:12]}... and {k.sha256[:12]}..."
        )
    if not k.in_bundle:
        return TraceCheck(k, True, f"{k.path}: outside the bundle, digest only (sha256 {k.sha256[:12]}...)")
    path = export_dir / k.path
    if not path.resolve().is_relative_to(export_dir.resolve()):
        return TraceCheck(k, False, f"{k.path} leads out of the export folder (a link to another file)")
    if not path.is_file():
        return TraceCheck(k, False, f"{k.path} is missing")
    now = sha256(path)
    if now != k.sha256:
        return TraceCheck(
            k, False, f"{k.path} changed: sha256 {now[:12]}..., the chain says {k.sha256[:12]}..."
        )
    try:
        parents = _recorded_parents(path, k)
        beside = recorded_coverage(read_json(path)) if k.name.startswith("HIL report") else {}
    except ValueError as exc:
        return TraceCheck(k, False, f"{k.path}: cannot read the hashes it records of its parents ({exc})")
    for name, recorded in beside.items():  # the node's coverage profiles and binary, beside the report
        file = path.parent / name
        if not file.is_file() or sha256(file) != recorded:
            said = "is missing" if not file.is_file() else f"changed (sha256 {sha256(file)[:12]}...)"
            return TraceCheck(k, False, f"{k.path} records {name} (sha256 {recorded[:12]}...), which {said}")
    for parent, recorded in parents.items():
        if parent.startswith("file ") and parent not in by_name:
            return TraceCheck(
                k, False, f"{k.path} records {parent.removeprefix('file ')}, which the chain does not link"
            )
        if parent in by_name and by_name[parent].sha256 != recorded:
            said = (
                f"records another {parent.removeprefix('file ')} (sha256 {recorded[:12]}...) than the chain's"
                if parent.startswith("file ")
                else f"was made from another {parent} (sha256 {recorded[:12]}...)"
            )
            return TraceCheck(k, False, f"{k.path} {said}")
    return TraceCheck(k, True, f"{k.path} sha256 {now[:12]}...")


_C_HEADER = re.compile(r"^ \* (source|onnx): (?:\S+ )?sha256 ([0-9a-f]{64})$", re.M)


def _recorded_parents(path: Path, k: TraceLink) -> dict[str, str]:
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
        records = {f"file {f}": h for f, h in files.items()}
        log = recorded_log(data) if k.name != "verification report" else None
        if log is not None:  # the frame log the run wrote
            records[f"file {log[0]}"] = log[1]
        return records
    return {}


def recorded_coverage(data: Any) -> dict[str, str]:
    """The coverage files a HIL report records (``hil run --coverage``), each as a path relative to the
    report's folder with its sha256; none for a run without coverage. ValueError for a record of another
    form, or a folder that is not one name beside the report."""
    record = data.get("coverage") if isinstance(data, dict) else None
    if record is None:
        return {}
    folder = record.get("folder") if isinstance(record, dict) else None
    if not isinstance(folder, str) or folder in ("", ".", "..") or "/" in folder or "\\" in folder:
        raise ValueError(f"its coverage folder {folder!r} is not one name beside the report")
    entries = [record.get("binary"), *(record.get("profiles") or [])]
    out = {}
    for entry in entries:
        file, digest = (entry.get("file"), entry.get("sha256")) if isinstance(entry, dict) else (None, None)
        if not isinstance(file, str) or not isinstance(digest, str) or "/" in file or file in ("", ".", ".."):
            raise ValueError(f"its coverage file {entry!r} is not an object of a file name and its sha256")
        out[f"{folder}/{file}"] = digest
    return out


def recorded_log(data: Any) -> tuple[str, str] | None:
    """The frame log a HIL report records, ``(its path in the bundle, its sha256)``; None if it records none.
    ValueError for a record of another form (a report is a file anyone can edit)."""
    log = data.get("log") if isinstance(data, dict) else None
    if log is None:
        return None
    file, digest = (log.get("file"), log.get("sha256")) if isinstance(log, dict) else (None, None)
    if not isinstance(file, str) or not isinstance(digest, str):
        raise ValueError(f"its log {log!r} is not an object of a file and its sha256")
    if not inside(file):
        raise ValueError(f"its log {file!r} is not a path inside the export folder")
    return file, digest
