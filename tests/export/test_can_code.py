"""The node's CAN code travels in the export (``can/``, ``can-fd/``): written by ``embedrl export`` from the
interface, chained and regenerated like ``c/``, and built by ``make -C runtime_c`` with no Python at all."""

from __future__ import annotations

import os
import shutil
import subprocess
from pathlib import Path

import pytest

from embedrl.common import read_json
from embedrl.export import chain, regenerate
from embedrl.export.build import RUNTIME_C
from embedrl.export.contract.interface_file import load_interface
from embedrl.export.contract.sources import C_FILES, DBC_FILE, FOLDERS, export_files
from embedrl.train.interface import Field, Interface
from embedrl.train.scenarios import STATIC
from tests.conftest import Exported

SHIPPED_TD3 = Path(__file__).resolve().parents[2] / "policies" / "static" / "td3.zip"
BUILD_TOOLS = ("make", "sh", "cc", "gcc", "as", "ld", "mkdir")
"""What ``make -C runtime_c node`` runs on the host: make, the shell of its recipes and the C toolchain."""
CROSS_TOOLS = (
    "arm-none-eabi-gcc",
    "arm-none-eabi-as",
    "arm-none-eabi-ld",
    "arm-none-eabi-objcopy",
    "arm-none-eabi-size",
)


@pytest.fixture
def export(exported: Exported) -> Path:
    """The shipped TD3 policy's export (the session's: read it, copy it before changing anything)."""
    return exported(SHIPPED_TD3, "--episodes", "0")


def _copy(export: Path, tmp_path: Path) -> Path:
    copy = tmp_path / "export"
    shutil.copytree(export, copy)
    return copy


def test_the_export_carries_the_can_code_of_its_interface_chained(export: Path) -> None:
    interface = load_interface(export / "interface.json")
    files, left_out = export_files(interface)
    assert left_out == []
    for folder in FOLDERS:
        assert sorted(p.name for p in (export / folder).iterdir()) == sorted((DBC_FILE, *C_FILES))
    for path, text in files.items():
        assert (export / path).read_bytes() == text.encode()  # the DBC's lines end in CR LF
    links = {k.name: k for k in chain.read(export)}
    recorded = read_json(export / "export_report.json")["files"]
    for path in files:
        assert links[f"CAN code {path}"].made_from == ["interface"]
        assert links[f"CAN code {path}"].path == path and path in recorded
    assert all(c.ok for c in chain.verify(export))


def test_an_interface_too_wide_for_classic_can_gets_its_can_fd_code_only() -> None:
    many = tuple(Field(f"o{i}", "", -1.0, 1.0) for i in range(60))
    wide = Interface("many", "Many-v0", many, (Field("a", "", -1.0, 1.0),), 0.1, (0.0,), 10)
    files, left_out = export_files(wide)
    assert {path.split("/")[0] for path in files} == {"can-fd"}
    assert left_out == ["no can/: 60 observation fields need 30 classic CAN frames; at most 26 (--fd carries "
                        "24 a frame)"]  # fmt: skip
    assert export_files(STATIC, "other") == ({}, [
        "no CAN code: the node runs the policy named 'policy', this one is 'other'"
    ])  # fmt: skip


@pytest.mark.parametrize("edit", ["append", "extra file", "missing file"])
def test_a_hand_edit_to_the_can_code_is_caught_like_one_to_the_policy(
    export: Path, tmp_path: Path, edit: str
) -> None:
    changed = _copy(export, tmp_path)
    glue = changed / "can" / "policy_io.c"
    if edit == "append":
        glue.write_text(glue.read_text() + "__attribute__((constructor)) static void run(void) {}\n")
        said = f"{glue} is not what embedrl generates from interface.json (edited since?)"
    elif edit == "extra file":
        (changed / "can-fd" / "extra.c").write_text("int x;\n")
        said = f"{changed / 'can-fd'} holds"
    else:
        glue.unlink()
        said = f"{changed / 'can'} holds"
    assert regenerate.mismatch(export) is None
    problem = regenerate.mismatch(changed)
    assert problem is not None and problem.startswith(said), problem
    if edit == "append":
        bad = [c for c in chain.verify(changed) if not c.ok]
        assert [c.link.name for c in bad] == ["CAN code can/policy_io.c"]


def test_an_export_made_before_it_carried_its_can_code_regenerates_but_make_refuses(
    export: Path, tmp_path: Path
) -> None:
    """An older export (no can/, no can-fd/): its C is still the generator's, so `hil run` may build it
    (with CAN code it generates itself); `make -C runtime_c node` alone says in one line what to do."""
    old = _copy(export, tmp_path)
    for folder in FOLDERS:
        shutil.rmtree(old / folder)
    assert regenerate.mismatch(old) is None
    result = _make(["node", f"POLICY_DIR={old / 'c'}", f"BUILD_DIR={tmp_path / 'build'}"], os.environ["PATH"])
    assert result.returncode == 2
    said = result.stderr.splitlines()[0]
    assert said == (
        f"no {old / 'c'}/../can/policy_dbc.c (the node's CAN code, which embedrl export writes beside c/): "
        "export the policy again, or set CAN_DIR"
    )
    lib = _make(["lib", f"POLICY_DIR={old / 'c'}", f"BUILD_DIR={tmp_path / 'lib'}"], os.environ["PATH"])
    assert lib.returncode == 0  # the policy alone needs no CAN code


def _toolchain_only(folder: Path, tools: tuple[str, ...]) -> str:
    """A PATH of one folder holding links to ``tools`` and nothing else: no Python on it."""
    folder.mkdir()
    for tool in tools:
        found = shutil.which(tool)
        assert found is not None, f"{tool} is not installed"
        (folder / tool).symlink_to(found)
    path = str(folder)
    assert shutil.which("python3", path=path) is None and shutil.which("python", path=path) is None
    return path


def _make(args: list[str], path: str) -> subprocess.CompletedProcess[str]:
    env = {"PATH": path, "HOME": os.environ.get("HOME", "/tmp"), "LANG": "C"}
    return subprocess.run(
        ["make", "--no-print-directory", "-C", str(RUNTIME_C), *args],
        capture_output=True, text=True, env=env, timeout=300,
    )  # fmt: skip


@pytest.mark.parametrize("fd", [False, True])
def test_make_builds_the_host_node_with_no_python_on_path(export: Path, tmp_path: Path, fd: bool) -> None:
    path = _toolchain_only(tmp_path / "bin", BUILD_TOOLS)
    args = ["node", f"POLICY_DIR={export / 'c'}", f"BUILD_DIR={tmp_path / 'build'}", f"FD={int(fd)}"]
    result = _make(args, path)
    assert result.returncode == 0, result.stdout + result.stderr
    assert (tmp_path / "build" / "policy_node").is_file()
    assert f"{'can-fd' if fd else 'can'}/policy_io.c" in result.stdout


@pytest.mark.skipif(shutil.which("arm-none-eabi-gcc") is None, reason="no arm-none-eabi-gcc (make deps)")
def test_make_builds_the_firmware_node_with_no_python_on_path(export: Path, tmp_path: Path) -> None:
    path = _toolchain_only(tmp_path / "bin", (*BUILD_TOOLS, *CROSS_TOOLS))
    args = ["TARGET=cortex-m4", "node", f"POLICY_DIR={export / 'c'}", f"BUILD_DIR={tmp_path / 'build'}"]
    result = _make(args, path)
    assert result.returncode == 0, result.stdout + result.stderr
    assert (tmp_path / "build" / "cortex-m4" / "node.elf").is_file()


def test_the_c_unit_tests_build_with_no_python_on_path(tmp_path: Path) -> None:
    """`make -C runtime_c test` compiles the committed static scenario's CAN code (tests/can_static)."""
    path = _toolchain_only(tmp_path / "bin", BUILD_TOOLS)
    result = _make(["test", f"BUILD_DIR={tmp_path / 'build'}"], path)
    assert result.returncode == 0, result.stdout + result.stderr
    assert "0 failures" in result.stdout
