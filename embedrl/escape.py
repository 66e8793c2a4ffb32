"""Text from users' files as data: one escaping function per output language.

A model's or a folder's text (ONNX node and tensor names, doc strings, an ``interface.json``'s descriptions,
a DBC's comments) never reaches generated C, a CAN database or a page as it came. Identifiers come from a
strict ``[A-Za-z0-9_]`` mapping (:func:`identifier`); comments carry a bounded copy from which every
character that could end the comment, continue its line or form a trigraph is gone (:func:`c_comment`); a
DBC's quoted strings the same (:func:`dbc_text`). HTML is escaped by the report's template engine (Jinja2
with autoescape), not here.
"""

from __future__ import annotations

import re

COMMENT_LIMIT = 80
"""Characters of user text one generated comment carries at most (longer text is cut, marked ``...``)."""
IDENTIFIER_LIMIT = 40
"""Characters of an identifier made from user text."""
_COMMENT_UNSAFE = re.compile(r"[^ -~]|[*\\?]")
"""Anything but printable ASCII, and ``*`` (ends or opens a comment), ``\\`` (a line continuation), ``?``
(trigraphs such as ``??/``)."""
_DBC_UNSAFE = re.compile(r"[^ -~]|[\"\\*?]")
"""A DBC string is double-quoted; cantools copies its comments into generated C comments."""
_NOT_IDENTIFIER = re.compile(r"[^A-Za-z0-9_]")
SUBSTITUTE = "_"
"""What an unsafe character becomes."""
ELLIPSIS = "..."


def _bounded(text: str, unsafe: re.Pattern[str], limit: int) -> str:
    flat = unsafe.sub(SUBSTITUTE, " ".join(text.split()))
    return flat if len(flat) <= limit else flat[: limit - len(ELLIPSIS)] + ELLIPSIS


def c_comment(text: str, limit: int = COMMENT_LIMIT) -> str:
    """``text`` as the body of a C block comment: one line of printable ASCII without ``*``, ``\\`` or
    ``?``, at most ``limit`` characters. Whitespace runs (newlines included) become one space."""
    return _bounded(text, _COMMENT_UNSAFE, limit)


def dbc_text(text: str, limit: int = COMMENT_LIMIT) -> str:
    """``text`` as a DBC string (a unit, a comment): :func:`c_comment`'s rule, and no double quote."""
    return _bounded(text, _DBC_UNSAFE, limit)


def identifier(text: str, limit: int = IDENTIFIER_LIMIT) -> str:
    """``text`` mapped to ``[A-Za-z0-9_]``, stripped of leading and trailing ``_``, at most ``limit``
    characters; ``v`` when nothing is left. The same text always gives the same identifier; an identifier
    gives itself (up to ``limit``)."""
    return _NOT_IDENTIFIER.sub(SUBSTITUTE, text).strip(SUBSTITUTE)[:limit] or "v"
