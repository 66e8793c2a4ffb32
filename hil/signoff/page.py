"""The deployment report as one self-contained HTML page: inline CSS and SVG, no scripts, no fonts, no
link that leaves the page. Each section has an ``id`` and each key figure a ``data-key``, which the
browser test reads back.

The page is rendered by Jinja2 with autoescape from the templates beside this file: the facts' text
(names, paths, details from an export folder and HIL reports) is always escaped; markup comes only from
the templates and from the figures matplotlib draws."""

from __future__ import annotations

import functools
from dataclasses import dataclass
from pathlib import Path
from typing import Any

import jinja2
from markupsafe import Markup

CSS = """
body { font-family: sans-serif; margin: 2em auto; max-width: 1100px; color: #222; line-height: 1.4; }
h1 { font-size: 1.6em; } h2 { border-bottom: 2px solid #ccc; margin-top: 2em; } h3 { margin-top: 1.4em; }
table { border-collapse: collapse; margin: 0.6em 0; font-size: 0.9em; }
th, td { border: 1px solid #ccc; padding: 3px 8px; text-align: left; vertical-align: top; }
th { background: #f0f0f0; } td.num { text-align: right; font-variant-numeric: tabular-nums; }
.ok { color: #1a7f37; font-weight: bold; } .fail { color: #c62828; font-weight: bold; }
.warn { color: #9a4b00; font-weight: bold; }
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


TEMPLATES = Path(__file__).parent / "templates"
"""The page's Jinja2 templates: ``page.html``, one file per section, ``macros.html`` (cells and tables)."""


@functools.cache
def _environment() -> jinja2.Environment:
    """Autoescape on every template: a value from the gathered facts is text, whatever it holds."""
    return jinja2.Environment(
        loader=jinja2.FileSystemLoader(TEMPLATES),
        autoescape=True,
        undefined=jinja2.StrictUndefined,
        trim_blocks=True,
        lstrip_blocks=True,
        keep_trailing_newline=False,
    )


@dataclass(frozen=True)
class Cell:
    """A table cell: a flag (yes/no), a number (right-aligned, formatted), text, or nothing (``-``); ``key``
    becomes its ``data-key`` for readers of the DOM."""

    text: str
    key: str | None = None
    numeric: bool = False
    flag: bool | None = None


def cell(value: Any, key: str | None = None) -> Cell:
    """The cell of ``value``: booleans as yes/no, None as ``-``, integers with thousands separators, other
    numbers to 4 significant digits, anything else as its text."""
    if isinstance(value, bool):
        return Cell("yes" if value else "no", key, flag=value)
    if value is None:
        return Cell("-", key)
    if isinstance(value, int | float):
        return Cell(f"{value:,}" if isinstance(value, int) else f"{value:.4g}", key, numeric=True)
    return Cell(str(value), key)


def fragment(template: str, **context: Any) -> Markup:
    """One template rendered with ``context`` (autoescaped), as markup another template may include."""
    return Markup(_environment().get_template(template).render(**context))


def svg(figure: str) -> Markup:
    """A figure matplotlib drew (its own SVG writer escapes text; labels are drawn as paths)."""
    return Markup(figure)


def page(title: str, intro: dict[str, Any], sections: dict[str, Markup], verdict: Markup) -> str:
    """The whole page: a title, a line of facts, the verdict, a table of contents and each section."""
    return (
        str(
            fragment(
                "page.html",
                title=title,
                intro=intro,
                css=Markup(CSS),
                verdict=verdict,
                sections=SECTIONS,
                bodies=sections,
            )
        )
        + "\n"
    )
