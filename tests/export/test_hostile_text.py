"""Text from a user's file never becomes code: arbitrary text in every text field of an ONNX model and of an
interface changes the generated C, headers and CAN database only inside comments and quoted DBC strings,
and those comments stay comments."""

from __future__ import annotations

import json
import re
import subprocess
from dataclasses import replace
from pathlib import Path

import cantools
import onnx
import pytest
from hypothesis import HealthCheck, given, settings
from hypothesis import strategies as st

from embedrl.export.codegen import generate
from embedrl.export.contract import sources as can_sources
from embedrl.export.errors import InvalidModelError
from embedrl.export.onnx_import import load_onnx
from embedrl.export.qdq import lowered
from embedrl.train.interface import Field, Interface, InterfaceError
from tests.export.test_golden import tiny_model

PAYLOADS = (
    '*/ __attribute__((constructor)) static void p(void) { system("id"); } /*',
    "a\nb\\\n#define X 1",
    "??/ trigraph ??= ??(",
    "\x00nul\x00",
    "x" * 100_000,
    "// line comment",
    "\u202e\u2028 bidi and line separator",
)
text = st.one_of(st.sampled_from(PAYLOADS), st.text(max_size=200))
_COMMENT_OR_STRING = re.compile(r'/\*.*?\*/|//[^\n]*|"(?:\\.|[^"\\\n])*"|\'(?:\\.|[^\'\\\n])*\'', re.S)


def _code(source: str) -> str:
    """``source`` with every comment replaced by one space (strings kept): what a compiler sees."""
    return _COMMENT_OR_STRING.sub(lambda m: " " if m.group(0).startswith("/") else m.group(0), source)


def _comments(source: str) -> list[str]:
    return [m.group(0) for m in _COMMENT_OR_STRING.finditer(source) if m.group(0).startswith("/*")]


def _hostile_model(texts: list[str]) -> onnx.ModelProto:
    """The tiny model with ``texts`` (cycled) as every name, doc string, producer and metadata value."""
    model = tiny_model()
    pick = iter(texts * 100)
    renames: dict[str, str] = {}
    graph = model.graph
    for tensor in graph.initializer:
        renames[tensor.name] = f"{next(pick)}#{len(renames)}"
    for node in graph.node:
        for out in node.output:
            if out not in renames and out != graph.output[0].name:
                renames[out] = f"{next(pick)}@{len(renames)}"
    renames[graph.input[0].name] = f"{next(pick)}!in"
    renames[graph.output[0].name] = f"{next(pick)}!out"
    for value in (*graph.input, *graph.output, *graph.value_info):
        value.name = renames.get(value.name, value.name)
        value.doc_string = next(pick)
    for tensor in graph.initializer:
        tensor.name = renames[tensor.name]
    for node in graph.node:
        node.name = next(pick)
        node.doc_string = next(pick)
        node.input[:] = [renames.get(i, i) for i in node.input]
        node.output[:] = [renames.get(o, o) for o in node.output]
    model.doc_string, graph.doc_string, graph.name = next(pick), next(pick), next(pick)
    model.producer_name, model.producer_version = next(pick), next(pick)
    onnx.helper.set_model_props(model, {next(pick)[:100] or "k": next(pick)})
    return model


def _interface(texts: list[str]) -> Interface:
    """A three-observation, two-action interface with ``texts`` in every free-text field (built directly:
    the file schema would refuse them; this is the generator's own defence)."""
    pick = iter(texts * 100)

    def fields(kind: str, n: int) -> tuple[Field, ...]:
        return tuple(Field(f"{kind}{i}", next(pick), -1.0, 1.0, next(pick)) for i in range(n))

    return Interface(next(pick), next(pick), fields("o", 3), fields("a", 2), 0.05, (0.0, 0.0), 100)


def _generated(model: onnx.ModelProto, interface: Interface, folder: Path) -> dict[str, str]:
    path = folder / "model.onnx"
    onnx.save(model, str(path))
    graph, _ = lowered(load_onnx(path))
    files = generate(graph, "policy", [0.0, 0.0], {"source": graph.input}, interface=interface)
    files.update(can_sources.export_files(interface)[0])
    return files


PLAIN_TEXT = ["plain"]


@settings(max_examples=25, deadline=None, suppress_health_check=[HealthCheck.function_scoped_fixture])
@given(texts=st.lists(text, min_size=1, max_size=6))
def test_hostile_text_changes_only_comments(tmp_path: Path, texts: list[str]) -> None:
    plain = _generated(tiny_model(), _interface(PLAIN_TEXT), tmp_path)
    hostile = _generated(_hostile_model(texts), _interface(texts), tmp_path)
    assert hostile.keys() == plain.keys()
    for name, source in hostile.items():
        if name.endswith(".dbc"):
            _same_database(source, plain[name])
            continue
        assert _code(source) == _code(plain[name]), name
        for comment in _comments(source):  # no trigraph (gcc -std=c99 reads them) nor a continued line
            assert "??" not in comment and "\\\n" not in comment, (name, comment[:80])


def _same_database(hostile: str, plain: str) -> None:
    """The same messages and signals, bit for bit; only comments, units and the version string differ."""
    a, b = cantools.database.load_string(hostile), cantools.database.load_string(plain)
    assert isinstance(a, cantools.database.can.Database) and isinstance(b, cantools.database.can.Database)
    assert [(m.name, m.frame_id, m.length) for m in a.messages] == [
        (m.name, m.frame_id, m.length) for m in b.messages
    ]
    for ma, mb in zip(a.messages, b.messages, strict=True):
        assert [(s.name, s.start, s.length, s.scale, s.minimum, s.maximum) for s in ma.signals] == [
            (s.name, s.start, s.length, s.scale, s.minimum, s.maximum) for s in mb.signals
        ]


def test_the_payload_compiles_to_the_plain_program(tmp_path: Path) -> None:
    """The comment-closing payload, compiled: gcc builds the hostile C, and its object code is the plain C's
    (a constructor the payload tried to add would be a new symbol)."""
    objects = []
    for label, model, interface in (
        ("plain", tiny_model(), _interface(PLAIN_TEXT)),
        ("hostile", _hostile_model(list(PAYLOADS)), _interface(list(PAYLOADS))),
    ):
        folder = tmp_path / label
        folder.mkdir()
        for name, source in _generated(model, interface, folder).items():
            if name in ("policy.c", "policy.h"):
                (folder / name).write_text(source)
        obj = folder / "policy.o"
        subprocess.run(
            [
                "gcc",
                "-std=c99",
                "-Wall",
                "-Wextra",
                "-Werror",
                "-c",
                str(folder / "policy.c"),
                "-o",
                str(obj),
            ],
            check=True,
        )
        symbols = subprocess.run(["nm", str(obj)], check=True, capture_output=True, text=True).stdout
        objects.append(sorted(line.split()[-1] for line in symbols.splitlines()))
    assert objects[0] == objects[1]


def test_non_utf8_names_are_refused_in_one_line(tmp_path: Path) -> None:
    model = tiny_model()
    model.graph.node[0].name = "MARKER"
    raw = model.SerializeToString().replace(b"MARKER", b"\xff\xfe*/\x00\x80\xc3")
    path = tmp_path / "bad.onnx"
    path.write_bytes(raw)
    try:
        graph, _ = lowered(load_onnx(path))
    except InvalidModelError as exc:
        assert "\n" not in str(exc)
    else:  # read with the bytes replaced: the name that reaches the IR is an identifier
        assert all(re.fullmatch(r"[A-Za-z0-9_]+", n.name) for n in graph.nodes)


@pytest.mark.parametrize(
    ("field", "value"),
    [
        ("name", "static */ int x;"),
        ("env_id", "os:system"),
        ("env_id", "x\ny"),
        ("description", "ends */ here"),
        ("unit", "m/s\\"),
        ("description", "??/"),
        ("description", "é"),
        ("description", "x" * 161),
        ("unit", 5),
    ],
)
def test_an_interface_file_with_unsafe_text_is_refused(field: str, value: object) -> None:
    data = json.loads(replace(_interface(PLAIN_TEXT), env_id="").dumps())
    Interface.from_json(data)  # as it came, the file reads
    if field in ("name", "env_id"):
        data[field] = value
    else:
        data["observation"][1][field] = value
    with pytest.raises(InterfaceError) as caught:
        Interface.from_json(data)
    assert "\n" not in str(caught.value) and len(str(caught.value)) < 400


def test_a_plain_interface_file_reads_back() -> None:
    interface = replace(_interface(PLAIN_TEXT), name="plain", env_id="embedrl/WarehouseRobot-v0")
    assert Interface.from_json(json.loads(interface.dumps())) == interface
