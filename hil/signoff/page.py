"""The deployment report as one self-contained HTML page: inline CSS and SVG, no scripts, no fonts, no
link that leaves the page. Each section has an ``id`` and each key figure a ``data-key``, which the
browser test reads back."""

from __future__ import annotations

from collections.abc import Iterable
from html import escape
from typing import Any

CSS = """
body { font-family: sans-serif; margin: 2em auto; max-width: 1100px; color: #222; line-height: 1.4; }
h1 { font-size: 1.6em; } h2 { border-bottom: 2px solid #ccc; margin-top: 2em; } h3 { margin-top: 1.4em; }
table { border-collapse: collapse; margin: 0.6em 0; font-size: 0.9em; }
th, td { border: 1px solid #ccc; padding: 3px 8px; text-align: left; vertical-align: top; }
th { background: #f0f0f0; } td.num { text-align: right; font-variant-numeric: tabular-nums; }
.ok { color: #1a7f37; font-weight: bold; } .fail { color: #c62828; font-weight: bold; }
.note { color: #555; font-size: 0.9em; } code { font-size: 0.9em; }
nav a { margin-right: 1em; } svg { max-width: 100%; height: auto; }
.pair { display: flex; gap: 2em; align-items: flex-start; }
details { margin: 0.2em 0; } summary { cursor: pointer; } ul.places { columns: 3; font-size: 0.85em; }
"""
SECTIONS = (
    ("conditions", "Measurement conditions"),
    ("interface", "Interface"),
    ("entry-points", "Entry points and call order"),
    ("verification", "Numerical verification"),
    ("closed-loop", "Closed loop"),
    ("layers", "Layer by layer"),
    ("resources", "Target resources"),
    ("coding-standard", "Coding standard"),
    ("coverage", "Coverage of the deployed C"),
    ("traceability", "Traceability chain"),
)


def cell(value: Any, key: str | None = None) -> str:
    """A table cell; numbers right-aligned, ``key`` as ``data-key`` for readers of the DOM."""
    attrs = f' data-key="{escape(key)}"' if key else ""
    if isinstance(value, bool) or value is None:
        text = {True: '<span class="ok">yes</span>', False: '<span class="fail">no</span>', None: "-"}[value]
        return f"<td{attrs}>{text}</td>"
    if isinstance(value, int | float):
        text = f"{value:,}" if isinstance(value, int) else f"{value:.4g}"
        return f'<td class="num"{attrs}>{text}</td>'
    return f"<td{attrs}>{escape(str(value))}</td>"


def table(headers: Iterable[str], rows: Iterable[Iterable[str]]) -> str:
    """``rows`` of cells made by :func:`cell` (already HTML)."""
    head = "".join(f"<th>{escape(h)}</th>" for h in headers)
    body = "".join(f"<tr>{''.join(r)}</tr>" for r in rows)
    return f"<table><tr>{head}</tr>{body}</table>"


def page(title: str, intro: str, sections: dict[str, str], verdict: str = "") -> str:
    """The whole page: a title, a line of facts, the verdict, a table of contents and each section's HTML."""
    nav = "".join(f'<a href="#{sid}">{escape(name)}</a>' for sid, name in SECTIONS)
    body = "".join(
        f'<section id="{sid}"><h2>{escape(name)}</h2>{sections[sid]}</section>' for sid, name in SECTIONS
    )
    return (
        '<!DOCTYPE html>\n<html lang="en"><head><meta charset="utf-8">'
        f"<title>{escape(title)}</title><style>{CSS}</style></head><body>"
        f"<h1>{escape(title)}</h1><p>{intro}</p>{verdict}<nav>{nav}</nav>{body}</body></html>\n"
    )
