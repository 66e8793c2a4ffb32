"""The deployment report (``embedrl report``): one self-contained HTML page an embedded team can sign
off, with the interface, the numerical verification, the closed loop on every platform, the target
resources, the coding standard and the traceability chain of one export."""

from __future__ import annotations

from pathlib import Path
from typing import Any

from embedrl.hil.errors import HilError


def gather(
    export_dir: Path, hil_reports: list[Path], also: list[Path], public_key: Any = None
) -> dict[str, Any]:
    """Every fact the page shows (its JSON form); bad inputs are refused before any work. The signature is
    checked against ``public_key`` if given."""
    from embedrl.export import chain, signature
    from embedrl.hil import misra
    from embedrl.hil.signoff import back_to_back, checks, conditions, facts, layers

    export = facts.load_export(export_dir)
    others = [(d, facts.load_export(d)) for d in also]
    for folder in also:
        facts.check_same_policy(export_dir, folder)
    hils = [(_shown(p, export_dir), facts.load_hil(p, export_dir)) for p in hil_reports]
    try:
        links = chain.verify(export_dir)
    except chain.ChainError as exc:
        raise HilError(str(exc)) from None
    with_paths = [(path, *h) for path, h in zip(hil_reports, hils, strict=True)]
    verification = [facts.recompute(folder, data) for folder, data in [(export_dir, export), *others]]
    gathered = {
        "export_dir": str(export_dir),
        "export": export,
        "interface": facts.interface_facts(export, export_dir),
        "verification": verification,
        "tolerance": export["verification"]["tolerance"],
        "closed_loop": facts.closed_loop_rows(export, hils),
        "hil_reports": [name for name, _ in hils],
        "targets": facts.target_facts(export, export_dir, [h for _, h in hils]),
        "coding_standard": misra.check(export_dir).to_json(),
        "layers": layers.layer_table(export_dir, export),
        "entry_points": conditions.entry_points(export_dir, export["name"]),
        "warnings": export["compiler"]["command"],
        "chain": [{**c.link.__dict__, "ok": c.ok, "detail": c.detail} for c in links],
        "signature": signature.check(export_dir, public_key).to_json(),
        "coverage": facts.coverage(export_dir, export, verification[0], with_paths),
        "back_to_back": back_to_back.links(export_dir, export, verification[0], hils),
    }
    tool = gathered["coding_standard"]["tool"]
    gathered["conditions"] = conditions.measurement_conditions(export, hils, tool, gathered["coverage"])
    gathered["verdict"] = checks.verdict(gathered, hils)
    return gathered


def render(data: dict[str, Any]) -> str:
    """The page of gathered facts ``data`` (autoescaped templates: :mod:`embedrl.hil.signoff.page`)."""
    from embedrl.hil.signoff import figures, page, sections

    data["figures"] = {
        "errors": figures.error_histograms({v["precision"]: v["errors"] for v in data["verification"]
                                            if len(v["errors"])}, data["tolerance"]),
        "closed_loop": figures.closed_loop(data["closed_loop"]) if data["closed_loop"] else "",
        "stack_and_memory": figures.stack_and_memory(data["targets"]) if data["targets"] else "",
    }  # fmt: skip
    export = data["export"]
    source = export["source"]
    intro = {
        "name": export["name"],
        "source": Path(source["path"]).name,
        "digest": source["sha256"][:16],
        "tool": export["tool"],
        "precision": data["verification"][0]["precision"],
        "ops": len(export["ops"]),
        "observations": export["observation_dim"],
        "actions": export["action_dim"],
    }
    body = {
        "conditions": sections.conditions(data),
        "interface": sections.interface(data),
        "entry-points": sections.entry_points(data),
        "layers": sections.layers(data),
        "verification": sections.verification(data),
        "closed-loop": sections.closed_loop(data),
        "resources": sections.resources(data),
        "coding-standard": sections.coding_standard(data),
        "coverage": sections.coverage(data),
        "traceability": sections.traceability(data),
    }
    title = f"Deployment report: {export['name']} ({data['interface']['name']})"
    return page.page(title, intro, body, sections.verdict(data))


def _shown(report: Path, export_dir: Path) -> str:
    """A HIL report's name on the page: its path in the bundle (else its file name)."""
    resolved, root = report.resolve(), export_dir.resolve()
    return resolved.relative_to(root).as_posix() if resolved.is_relative_to(root) else report.name


def write(
    export_dir: Path,
    hil_reports: list[Path],
    also: list[Path],
    out: Path,
    sign: Path | None = None,
    key: Path | None = None,
) -> dict[str, Any]:
    """Gather the HIL reports into the bundle, sign its chain with the private key ``sign`` if given (when
    the chain is intact), gather, render and write the page atomically; the facts, for the caller's summary.
    The signature is checked against the public key ``key`` (else ``sign``'s)."""
    from embedrl.common import atomic_write
    from embedrl.export import chain, signature
    from embedrl.hil.signoff import bundle, facts

    private = signature.load_private_key(sign) if sign else None  # bad keys before any work
    public = signature.load_public_key(key) if key else private.public_key() if private else None
    for report in hil_reports:
        facts.load_hil(report, export_dir)
    hil_reports = bundle.gather(export_dir, hil_reports)
    if private is not None:
        try:
            intact = all(c.ok for c in chain.verify(export_dir))
        except chain.ChainError as exc:
            raise HilError(str(exc)) from None
        if intact:
            signature.sign(export_dir, private)
    data = gather(export_dir, hil_reports, also, public)
    html = render(data)
    atomic_write(out, lambda tmp: tmp.write_text(html))
    return data
