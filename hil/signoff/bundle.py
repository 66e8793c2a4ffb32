"""The report cites only files of its bundle: HIL reports written elsewhere are copied into the export
folder's ``hil/`` and their chain links point there, so the export folder, copied or moved, still holds
every piece of evidence its page shows."""

from __future__ import annotations

import os
import shutil
from pathlib import Path, PurePosixPath

from embedrl.common import sha256
from embedrl.hil.errors import HilError


def gather(export_dir: Path, hil_reports: list[Path]) -> list[Path]:
    """Each HIL report's path inside the bundle, copying in (and linking into the chain) those outside it,
    the frame log each records (found in the bundle or beside the report) and its coverage folder. HilError
    (one line) for a report that cannot join the bundle; nothing is copied then."""
    from embedrl.common import read_json
    from embedrl.export import chain
    from embedrl.hil.coverage import recorded_files
    from embedrl.hil.run import in_bundle, link_report

    if not (export_dir / chain.MANIFEST).is_file():
        return hil_reports  # no chain, no bundle to make
    places = [in_bundle(export_dir, report) for report in hil_reports]
    copies: list[tuple[Path, Path]] = []  # (a file from outside, its place in the bundle)
    for report, place in zip(hil_reports, places, strict=True):
        if place == report:
            continue
        if places.count(place) > 1:
            raise HilError(f"cannot gather {report} into the bundle: two HIL reports named {report.name}")
        _check_place(report, report, place)
        copies.append((report, place))
        data = read_json(report)
        log = _log_of(export_dir, report, data)
        if log is not None:
            copies.append(log)
        copies.extend(recorded_files(report, place, data))  # its coverage folder (the digests: the report's)
    if copies and not os.access(export_dir, os.W_OK | os.X_OK):
        raise HilError(
            f"cannot gather {copies[0][0]} into the bundle: {export_dir} is not writable (the report cites "
            "only files inside the export folder; copy the HIL report into it)"
        )
    for file, place in copies:
        if not place.exists():
            place.parent.mkdir(parents=True, exist_ok=True)
            partial = place.with_name(f".{place.name}.partial")
            shutil.copyfile(file, partial)
            os.replace(partial, place)
    links = {k.name: k for k in chain.read(export_dir)}
    for place in places:
        known = links.get(f"HIL report {place.relative_to(export_dir).as_posix()}")
        if known is None or known.sha256 != sha256(place):
            link_report(export_dir, place, read_json(place))
    return places


def _check_place(report: Path, file: Path, place: Path) -> None:
    if place.exists() and (not place.is_file() or place.read_bytes() != file.read_bytes()):
        raise HilError(
            f"cannot gather {report} into the bundle: {place} holds another file (rename one of them)"
        )


def _log_of(export_dir: Path, report: Path, data: object) -> tuple[Path, Path] | None:
    """The frame log a report from outside records, to copy from beside it to the place the report names
    in the bundle (None if the bundle holds it already); HilError if it is in neither place with the digest
    the report records."""
    from embedrl.export import chain

    try:
        log = chain.recorded_log(data)
    except ValueError as exc:
        raise HilError(f"{report}: {exc}") from None
    if log is None:
        return None
    file, digest = log
    place = export_dir / file
    if place.is_file() and sha256(place) == digest:
        return None
    beside = report.parent / PurePosixPath(file).name
    if not beside.is_file() or sha256(beside) != digest:
        raise HilError(
            f"cannot gather {report} into the bundle: the frame log it records, {beside.name} (sha256 "
            f'{digest[:12]}...), is not beside it (give the report with its log, or without its "log" record)'
        )
    _check_place(report, beside, place)
    return beside, place
