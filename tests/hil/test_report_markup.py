"""Text from an export folder is text on the page: an HTML payload in every string the report reads adds no
element or attribute to it and makes it fetch nothing."""

from __future__ import annotations

import copy
from html.parser import HTMLParser
from pathlib import Path
from typing import Any

import pytest

from embedrl.hil import signoff
from tests.conftest import Exported, marks_its_users

SHIPPED_TD3 = Path(__file__).resolve().parents[2] / "policies" / "static" / "td3.zip"
PAYLOAD = '--><!--<img src=//evil.example/x onerror=alert(1)>"\'><script>fetch("//e")</script><a href=//e>'


class _Markup(HTMLParser):
    """Every element and attribute of a page, and every address it would fetch or link to."""

    def __init__(self) -> None:
        super().__init__(convert_charrefs=True)
        self.elements: set[str] = set()
        self.attributes: set[tuple[str, str]] = set()
        self.addresses: list[str] = []
        self.comments: list[str] = []

    def handle_starttag(self, tag: str, attrs: list[tuple[str, str | None]]) -> None:
        self.elements.add(tag)
        for name, value in attrs:
            self.attributes.add((tag, name))
            if name in ("src", "href", "action", "srcset", "poster") and value and not value.startswith("#"):
                self.addresses.append(value)

    def handle_comment(self, data: str) -> None:
        self.comments.append(data)


def _parsed(html: str) -> _Markup:
    parser = _Markup()
    parser.feed(html)
    parser.close()
    return parser


KEPT = ("target",)
"""A target's name: one of the known targets, which the export report's schema checks (a name it refuses
cannot reach the page)."""


def _poisoned(value: Any) -> Any:
    """``value`` with every string in it (not the keys, nor a target's name) replaced by the payload."""
    if isinstance(value, str):
        return PAYLOAD
    if isinstance(value, dict):
        return {k: v if k in KEPT else _poisoned(v) for k, v in value.items()}
    if isinstance(value, list | tuple):
        return [_poisoned(v) for v in value]
    return value


@pytest.fixture(scope="module")
@marks_its_users("slow", "qemu")  # the export runs the M4 firmware on QEMU: the page's target section
def gathered(exported: Exported) -> dict[str, Any]:
    return signoff.gather(exported(SHIPPED_TD3, "--episodes", "0", "--target", "cortex-m4"), [], [])


def _texts(value: Any) -> int:
    if isinstance(value, str):
        return 1
    if isinstance(value, dict):
        return sum(_texts(v) for v in value.values())
    return sum(_texts(v) for v in value) if isinstance(value, list | tuple) else 0


@pytest.mark.parametrize(
    "section",
    ["export", "interface", "verification", "coding_standard", "layers", "entry_points", "chain", "signature",
     "coverage", "back_to_back", "conditions", "verdict", "export_dir", "warnings", "closed_loop", "targets"],
)  # fmt: skip
def test_a_payload_in_every_string_adds_no_markup(gathered: dict[str, Any], section: str) -> None:
    plain = _parsed(signoff.render(copy.deepcopy(gathered)))
    data = copy.deepcopy(gathered)
    data[section] = _poisoned(data[section])
    poisoned = signoff.render(data)
    found = _parsed(poisoned)
    assert found.elements <= plain.elements, found.elements - plain.elements
    assert found.attributes <= plain.attributes, found.attributes - plain.attributes
    assert found.addresses == [] and found.comments == []
    assert "<script" not in poisoned and "<img" not in poisoned
    if _texts(gathered[section]):  # the payload is on the page, as text (a section without text: no HIL run)
        assert "&lt;img src=//evil.example/x" in poisoned
