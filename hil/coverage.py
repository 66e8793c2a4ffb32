"""The C node's coverage in a HIL run (``embedrl hil run --coverage``): the node built with clang's coverage
flags (``make -C runtime_c coverage-node``) runs in the sandbox as the plain node does; each of its processes
writes a raw profile (``LLVM_PROFILE_FILE``, one file per process) into a folder the guest and the host share
when it exits, on its own or stopped by the harness (SIGTERM: ``main`` returns). A process killed by SIGKILL
(the ``kill`` faults) writes none. The host keeps the readable profiles and the instrumented binary (whose
coverage mapping ``llvm-cov`` reads; it never runs it) in the run's coverage folder, and the HIL report
records them with their digests; ``embedrl report`` merges them with the C tests' and the verification
vectors' profiles (:mod:`embedrl.hil.signoff.coverage`).
"""

from __future__ import annotations

import shutil
import subprocess
from pathlib import Path
from typing import Any

from embedrl.common import sha256
from embedrl.hil.errors import HilError

PROFILES = "coverage"
"""The folder of the session's scratch space where the guest's node writes its profiles."""
PROFILE_PATTERN = "node-%p.profraw"
"""``LLVM_PROFILE_FILE``: one raw profile per node process (``%p``: its process id)."""
BINARY = "policy_node"
"""The instrumented node's name in the coverage folder."""
FOLDER_SUFFIX = ".coverage"
"""The coverage folder of a HIL report ``NAME.json`` is ``NAME.coverage`` beside it."""
LLVM_PROFDATA = "llvm-profdata-19"
FLAGS_GOAL = "coverage-flags"
"""The make goal that prints the coverage builds' compiler and flags."""


def folder_of(report: Path) -> Path:
    """The coverage folder beside a HIL report (``hil.json`` -> ``hil.coverage``)."""
    return report.with_suffix(FOLDER_SUFFIX)


def is_coverage_file(path: Path) -> bool:
    """Whether a file is one :func:`keep` writes (a raw profile or the binary)."""
    return path.is_file() and (path.suffix == ".profraw" or path.name == BINARY)


def keep(written: Path, binary: Path, folder: Path) -> dict[str, Any]:
    """Copy the readable raw profiles in ``written`` and the instrumented ``binary`` into ``folder``; the
    record the HIL report keeps (file names relative to ``folder``, their digests, the unreadable ones, the
    compiler and flags the node was built with)."""
    from embedrl.export import build

    profiles = sorted(written.glob("*.profraw")) if written.is_dir() else []
    readable = [p for p in profiles if _readable(p)]
    folder.mkdir(parents=True, exist_ok=True)
    for earlier in folder.glob("*.profraw"):  # an earlier run's, whose report this run's replaces
        earlier.unlink()
    for file in [*readable, binary]:
        shutil.copyfile(file, folder / (BINARY if file == binary else file.name))
    return {
        "folder": folder.name,
        "binary": {"file": BINARY, "sha256": sha256(folder / BINARY)},
        "profiles": [{"file": p.name, "sha256": sha256(folder / p.name)} for p in readable],
        "unreadable": [p.name for p in profiles if p not in readable],
        "compiler": build.compiler(goal=FLAGS_GOAL),
    }


def _readable(profile: Path) -> bool:
    """Whether llvm-profdata reads the raw profile (one cut short by a kill is not)."""
    result = subprocess.run([LLVM_PROFDATA, "show", str(profile)], capture_output=True, text=True)
    return result.returncode == 0


def sources(report: Path, data: dict[str, Any]) -> tuple[Path, list[Path]]:
    """The instrumented binary and the raw profiles a HIL report records, found in its coverage folder
    (:func:`folder_of`) with the recorded digests; HilError (one line) naming what is missing or changed."""
    record = data.get("coverage")
    if data.get("node") not in (None, "c"):
        raise HilError(f"{report.name}: a {data['node']} node run (coverage measures the C node: --node c)")
    if not isinstance(record, dict) or not isinstance(record.get("profiles"), list):
        raise HilError(f"{report.name}: a run without coverage (embedrl hil run --coverage)")
    folder = folder_of(report)
    files = [record["binary"], *record["profiles"]]
    for entry in files:
        file = folder / str(entry["file"])
        if not file.is_file():
            raise HilError(f"{report.name}: its coverage file {file.name} is not in {folder}")
        if sha256(file) != entry["sha256"]:
            raise HilError(f"{report.name}: its coverage file {file.name} changed since the run (sha256)")
    if not record["profiles"]:
        raise HilError(f"{report.name}: the run's node wrote no readable profile")
    return folder / BINARY, [folder / str(p["file"]) for p in record["profiles"]]


def recorded_files(report: Path, place: Path, data: dict[str, Any]) -> list[tuple[Path, Path]]:
    """The coverage files a HIL report records, each beside ``report`` and at its place beside the report's
    copy ``place`` in the bundle (none for a run without coverage)."""
    record = data.get("coverage")
    if not isinstance(record, dict):
        return []
    names = [str(entry["file"]) for entry in [record.get("binary", {}), *record.get("profiles", [])] if entry]
    return [(folder_of(report) / name, folder_of(place) / name) for name in names]
