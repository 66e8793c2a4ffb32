"""The house's structure, read from the source: the import graph (every import, function-level ones too),
the layers' direction, thin command modules and short functions.

The modules come under their import names from pyproject.toml's package map (``tests/source_tree.py``),
so the graph holds every file of ``train/``, ``export/`` and ``hil/``.
"""

from __future__ import annotations

import ast
import dataclasses
import re
from pathlib import Path

import pytest

from tests.source_tree import REPO, modules

LAYERS = (
    "embedrl.common",
    "embedrl.train",
    "embedrl.export.contract",
    "embedrl.export",
    "embedrl.hil",
    "embedrl.cli",
    "embedrl.__main__",
)
"""Bottom to top: a module imports only from its own layer or the ones below (``python -m embedrl`` runs the
command). A module is in the layer of the longest name it starts with: the contract (the interface's CAN
layout, DBC, E2E parameters and C glue) is the bottom of the export package, below the rest of it and hil."""
ENTRY_POINTS = ("embedrl.cli", "embedrl.__main__")
MAX_FUNCTION_LINES = 80


def _imports(name: str, path: Path, known: set[str]) -> set[str]:
    """The project's modules ``name`` imports, anywhere in the file (a ``from package import module``
    counts as the module)."""
    package = name if path.name == "__init__.py" else name.rpartition(".")[0]
    found = set()
    for node in ast.walk(ast.parse(path.read_text())):
        if isinstance(node, ast.Import):
            found |= {a.name for a in node.names}
        elif isinstance(node, ast.ImportFrom):
            base = package.split(".")[: len(package.split(".")) - node.level + 1] if node.level else []
            module = ".".join([*base, node.module] if node.module else base)
            found |= {f"{module}.{a.name}" if f"{module}.{a.name}" in known else module for a in node.names}
    return {m for m in found if m in known and m != name}


def import_graph() -> dict[str, set[str]]:
    """Module -> the project's modules it imports, for the library (not the tests)."""
    files = modules(with_tests=False)
    return {name: _imports(name, path, set(files)) for name, path in files.items()}


def _layer(module: str) -> int:
    """The module's layer: the longest of :data:`LAYERS` it is or is inside (``embedrl`` itself, the
    version, sits at the bottom)."""
    found = [layer for layer in LAYERS if module == layer or module.startswith(layer + ".")]
    return LAYERS.index(max(found, key=len)) if found else 0


def _cycles(graph: dict[str, set[str]]) -> list[list[str]]:
    """Strongly connected components of more than one module (Tarjan)."""
    index: dict[str, int] = {}
    low: dict[str, int] = {}
    stack: list[str] = []
    found = []

    def visit(v: str) -> None:
        index[v] = low[v] = len(index)
        stack.append(v)
        for w in graph[v]:
            if w not in index:
                visit(w)
                low[v] = min(low[v], low[w])
            elif w in stack:
                low[v] = min(low[v], index[w])
        if low[v] == index[v]:
            component = []
            while True:
                w = stack.pop()
                component.append(w)
                if w == v:
                    break
            if len(component) > 1:
                found.append(sorted(component))

    for v in sorted(graph):
        if v not in index:
            visit(v)
    return found


def test_the_graph_sees_every_file_of_every_package() -> None:
    graph = import_graph()
    for folder, package in (("train", "embedrl.train"), ("export", "embedrl.export"), ("hil", "embedrl.hil")):
        files = sorted((REPO / folder).rglob("*.py"))
        assert len([m for m in graph if m.startswith(package + ".") or m == package]) == len(files), folder
    assert "embedrl.export.ops.linear" in graph and "embedrl.hil.sandbox.uml" in graph
    assert "embedrl.export.ir" in graph["embedrl.export.interpret"]  # arrows inside a package too
    assert not list((REPO / "embedrl").glob("*/")), "embedrl/ holds modules only: the packages are mapped"


def test_no_import_cycles() -> None:
    assert _cycles(import_graph()) == []


def test_the_cycle_finder_finds_a_cycle() -> None:
    assert _cycles({"a": {"b"}, "b": {"c"}, "c": {"a"}, "d": {"a"}}) == [["a", "b", "c"]]


def test_lower_layers_never_import_upper_ones() -> None:
    upward = [
        f"{module} -> {target}"
        for module, targets in import_graph().items()
        for target in targets
        if _layer(target) > _layer(module)
    ]
    assert upward == []


def test_the_layer_of_a_module_is_its_longest_prefix() -> None:
    assert _layer("embedrl.export.contract.dbc") < _layer("embedrl.export.codegen") < _layer("embedrl.hil")
    assert _layer("embedrl.train.interface") < _layer("embedrl.export.contract")
    assert _layer("embedrl.export.contracts") == _layer("embedrl.export")


def test_the_contract_is_imported_from_its_own_home() -> None:
    """hil reads the contract where it lives: no module of hil or export is left from the old
    ``hil/candb.py`` (or any other copy), and both hil and export use the contract."""
    graph = import_graph()
    assert "embedrl.hil.candb" not in graph
    contract = {m for m in graph if m.startswith("embedrl.export.contract")}
    users = {m.rpartition(".")[0] for m, targets in graph.items() if targets & contract and m not in contract}
    assert {"embedrl.hil", "embedrl.export"} <= users


def _code_lines(text: str, comment: str) -> list[str]:
    return [line for line in text.splitlines() if not line.lstrip().startswith(comment)]


def test_export_reaches_hil_by_no_route_the_import_graph_cannot_see() -> None:
    """No subprocess route from export (or from the C build it runs) into hil: no file of export/ names
    an ``embedrl.hil`` module, and runtime_c's Makefile runs no Python and generates nothing (the export
    writes all the C, so ``make -C runtime_c`` needs make and the C toolchain only)."""
    named = [
        str(path.relative_to(REPO))
        for path in sorted((REPO / "export").rglob("*.py"))
        if "embedrl.hil" in path.read_text() or "embedrl/hil" in path.read_text()
    ]
    assert named == []
    makefile = _code_lines((REPO / "runtime_c" / "Makefile").read_text(), "#")
    assert not [line for line in makefile if re.search(r"python|PYTHON|embedrl\.|-m\s+\w", line)]
    for mk in sorted((REPO / "runtime_c").rglob("*.mk")):
        assert not [line for line in _code_lines(mk.read_text(), "#") if re.search(r"python", line, re.I)]


def test_no_library_module_imports_a_command_module() -> None:
    graph = import_graph()
    commands = {m for m in graph if m.rpartition(".")[2] == "cli"}
    offenders = {
        m: sorted(graph[m] & commands) for m in graph if m not in ENTRY_POINTS and graph[m] & commands
    }
    assert offenders == {}
    assert commands >= {"embedrl.train.cli", "embedrl.export.cli", "embedrl.hil.cli"}


def _long_functions(path: Path) -> list[str]:
    tree = ast.parse(path.read_text())
    return [
        f"{path.relative_to(REPO)}:{node.lineno} {node.name} ({node.end_lineno - node.lineno + 1} lines)"
        for node in ast.walk(tree)
        if isinstance(node, ast.FunctionDef | ast.AsyncFunctionDef)
        and node.end_lineno is not None
        and node.end_lineno - node.lineno + 1 > MAX_FUNCTION_LINES
    ]


@pytest.mark.parametrize("folder", ["train", "export", "hil", "embedrl"])
def test_no_function_is_longer_than_80_lines(folder: str) -> None:
    assert [f for path in sorted((REPO / folder).rglob("*.py")) for f in _long_functions(path)] == []


SCENARIO_NAME = re.compile(r"""["'](static|moving-shelf|two-robots)["']""")


@pytest.mark.parametrize("folder", ["train", "export", "hil", "embedrl"])
def test_scenario_names_are_typed_only_in_their_specs(folder: str) -> None:
    """Code names a scenario through its spec (``TWO_ROBOTS.name``, ``DEFAULT_SCENARIO``), so the spec
    module is the one place a scenario's name is written."""
    typed = [
        f"{path.relative_to(REPO)}:{n + 1}"
        for path in sorted((REPO / folder).rglob("*.py"))
        if path != REPO / "train" / "scenarios.py"
        for n, line in enumerate(path.read_text().splitlines())
        if SCENARIO_NAME.search(line.split("#")[0])
    ]
    assert typed == []


SCENARIO_IDENTITY = re.compile(
    r"(==|!=|\bis|\bin)\s*\(?\s*[A-Z_]*TWO_ROBOTS\b|\bTWO_ROBOTS(\.\w+)?\s*(==|!=|\bis\b)"
)


def _identity_checks(path: Path) -> list[str]:
    return [
        f"{path.relative_to(REPO)}:{n + 1}"
        for n, line in enumerate(path.read_text().splitlines())
        if SCENARIO_IDENTITY.search(line.split("#")[0])
    ]


@pytest.mark.parametrize("folder", ["train", "export", "hil", "embedrl"])
def test_no_code_compares_against_the_two_robot_scenario(folder: str) -> None:
    """Code asks a scenario's properties (``spec.robots``), never whether it is the two-robot scenario, so a
    second scenario with several robots touches no check."""
    found = [
        c
        for path in sorted((REPO / folder).rglob("*.py"))
        if path.name != "scenarios.py"
        for c in _identity_checks(path)
    ]
    assert found == []


def test_the_identity_check_finder_finds_one(tmp_path: Path) -> None:
    sample = REPO / "tests" / "_identity_sample.py"
    lines = [
        "if env_id == TWO_ROBOTS.env_id:",
        "if spec is TWO_ROBOTS:",
        "if TWO_ROBOTS.name == s:",
        "x = TWO_ROBOTS.obs_low",
    ]
    try:
        sample.write_text("\n".join(lines) + "\n")
        assert _identity_checks(sample) == [f"tests/_identity_sample.py:{n}" for n in (1, 2, 3)]
    finally:
        sample.unlink()


def test_every_scenario_with_several_robots_has_a_team_env() -> None:
    from embedrl.train.scenarios import SCENARIOS, TEAM_ENVS, team_env

    several = {name for name, spec in SCENARIOS.items() if spec.robots > 1}
    assert several and set(TEAM_ENVS) == several
    for name in several:
        env = team_env(SCENARIOS[name])
        try:
            assert len(env.possible_agents) == SCENARIOS[name].robots
        finally:
            env.close()


NODE_KIND_LITERAL = re.compile(
    r"""(==|!=|\bin)\s*\(?\s*["'](c|firmware|python)["']|["'](c|firmware|python)["']\s*(==|!=)"""
)


def _node_kind_comparisons(path: Path) -> list[str]:
    return [
        f"{path.relative_to(REPO)}:{n + 1}"
        for n, line in enumerate(path.read_text().splitlines())
        if NODE_KIND_LITERAL.search(line.split("#")[0])
    ]


def test_no_code_compares_a_node_kind_by_name() -> None:
    """What differs between node kinds is a field or hook of its :class:`NodeKind`, so adding a kind is one
    entry of ``NODE_KINDS``."""
    found = [
        c
        for folder in ("hil", "export", "embedrl")
        for path in sorted((REPO / folder).rglob("*.py"))
        if path.name != "node_kinds.py"
        for c in _node_kind_comparisons(path)
    ]
    assert found == []


def test_the_node_kind_comparison_finder_finds_one() -> None:
    sample = REPO / "tests" / "_node_kind_sample.py"
    lines = ['if options.node == "firmware":', 'if cfg.node != "c":', "if 'python' == kind:", 'd = {"c": 1}']
    try:
        sample.write_text("\n".join(lines) + "\n")
        assert _node_kind_comparisons(sample) == [f"tests/_node_kind_sample.py:{n}" for n in (1, 2, 3)]
    finally:
        sample.unlink()


def test_every_node_kind_is_complete_and_accepted_by_the_cli() -> None:
    import argparse

    from embedrl.cli import build_parser
    from embedrl.hil.node_kinds import DEFAULT_NODE, NODE_KINDS, NodeKind
    from embedrl.hil.options import RunOptions

    option_names = {f.name for f in dataclasses.fields(RunOptions)}
    assert DEFAULT_NODE in NODE_KINDS
    for name, kind in NODE_KINDS.items():
        assert isinstance(kind, NodeKind) and kind.called and kind.help and callable(kind.start), name
        assert set(kind.refuses) <= option_names, name
        assert kind.in_sandbox or not (kind.host_binary or kind.firmware_image), name
        assert not kind.builds_c or kind.runs_on, f"{name}: a kind that runs C says where"
        args = build_parser().parse_args(["hil", "run", "--export-dir", "x", "--node", name])
        assert isinstance(args, argparse.Namespace) and args.node == name


def test_every_sandbox_provider_is_complete_and_every_list_derives_from_the_registry() -> None:
    from embedrl.cli import build_parser
    from embedrl.hil import sandbox

    names = [p.name for p in sandbox.PROVIDERS]
    assert (sandbox.AUTO, *names) == sandbox.MODES and len(set(names)) == len(names)
    help_text = sandbox.mode_help()
    for p in sandbox.PROVIDERS:
        assert p.summary and p.debian and callable(p.candidates), p.name
        assert f"{p.name}: {p.summary}" in help_text
        assert set(p.debian) <= set(sandbox.debian_packages())
        assert all(found.name == p.name for found in p.candidates()), p.name
        for command in (
            ["hil", "run", "--export-dir", "x"],
            ["hil", "doctor"],
            ["hil", "bench", "--export-dir", "x"],
        ):
            assert build_parser().parse_args([*command, "--sandbox", p.name]).sandbox == p.name
    makefile = (REPO / "Makefile").read_text()
    assert "debian_packages()" in makefile, "make apt-packages installs what the providers need"
    listed = re.search(r"^APT_PACKAGES := ((?:.*\\\n)*.*)$", makefile, re.M)
    assert listed is not None
    assert not set(listed.group(1).replace("\\\n", " ").split()) & set(sandbox.debian_packages()), (
        "listed twice"
    )


def test_every_target_has_its_board_and_is_a_choice_of_the_commands() -> None:
    from embedrl.cli import build_parser
    from embedrl.export.target import TARGETS

    assert TARGETS
    for name, target in TARGETS.items():
        assert (REPO / "runtime_c" / "cortex_m" / "boards" / target.board / "board.h").is_file(), name
        assert build_parser().parse_args(["export", "m.zip", "--out", "x", "--target", name]).target == [name]
        hil_args = ["hil", "run", "--export-dir", "x", "--node", "firmware", "--target", name]
        assert build_parser().parse_args(hil_args).target == name


def test_no_two_library_classes_share_a_name() -> None:
    """A class name means one thing across the packages (a CAN link and a traceability link, a policy node
    and a graph node, have names of their own)."""
    where: dict[str, list[str]] = {}
    for folder in ("train", "export", "hil", "embedrl"):
        for path in sorted((REPO / folder).rglob("*.py")):
            for node in ast.walk(ast.parse(path.read_text())):
                if isinstance(node, ast.ClassDef):
                    where.setdefault(node.name, []).append(str(path.relative_to(REPO)))
    assert {name: paths for name, paths in where.items() if len(paths) > 1} == {}
