"""The report cites only files of its bundle: HIL reports written elsewhere are copied into the export
folder's ``hil/`` and their chain links point there, so the export folder, copied or moved, still holds
every piece of evidence its page shows."""

from __future__ import annotations

import os
import shutil
from pathlib import Path

from embedrl.common import sha256
from embedrl.hil.errors import HilError


def gather(export_dir: Path, hil_reports: list[Path]) -> list[Path]:
    """Each HIL report's path inside the bundle, copying in (and linking into the chain) those outside it.
    HilError (one line) for a report that cannot join the bundle; nothing is copied then."""
    from embedrl.common import read_json
    from embedrl.export import chain
    from embedrl.hil.run import in_bundle, link_report

    if not (export_dir / chain.MANIFEST).is_file():
        return hil_reports  # no chain, no bundle to make
    places = [in_bundle(export_dir, report) for report in hil_reports]
    for report, place in zip(hil_reports, places, strict=True):
        if place == report:
            continue
        if place.exists() and (not place.is_file() or place.read_bytes() != report.read_bytes()):
            raise HilError(
                f"cannot gather {report} into the bundle: {place} holds another file (rename one of them)"
            )
        if places.count(place) > 1:
            raise HilError(f"cannot gather {report} into the bundle: two HIL reports named {report.name}")
        if not place.exists() and not os.access(export_dir, os.W_OK | os.X_OK):
            raise HilError(
                f"cannot gather {report} into the bundle: {export_dir} is not writable (the report cites "
                "only files inside the export folder; copy the HIL report into it)"
            )
    links = {k.name: k for k in chain.read(export_dir)}
    for report, place in zip(hil_reports, places, strict=True):
        if not place.exists():
            place.parent.mkdir(exist_ok=True)
            partial = place.with_name(f".{place.name}.partial")
            shutil.copyfile(report, partial)
            os.replace(partial, place)
        known = links.get(f"HIL report {place.relative_to(export_dir).as_posix()}")
        if known is None or known.sha256 != sha256(place):
            link_report(export_dir, place, read_json(place))
    return places
