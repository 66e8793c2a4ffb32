"""The HIL contract against the Python reference node on python-can's virtual bus: no kernel, no build.

Every session-logic path (lock-step, faults, the safe action, real-time pacing) runs here in seconds;
the same suite runs against the compiled node over SocketCAN in ``test_hil_vcan.py``.
"""

from __future__ import annotations

import shutil
from pathlib import Path

import pytest

from embedrl.cli import main
from tests.hil.contract import HilContract


class TestPythonNodeOnVirtualBus(HilContract):
    node = "python"
    sandboxes = ("none",)
    channel = "embedrl-"


def test_an_export_without_an_interface_is_a_clear_error(
    export_dir: Path, tmp_path: Path, capsys: pytest.CaptureFixture[str]
) -> None:
    old = tmp_path / "old-export"
    shutil.copytree(export_dir, old)
    (old / "interface.json").unlink()
    assert main(["hil", "run", "--export-dir", str(old), "--json", str(tmp_path / "x.json")]) == 2
    assert "no interface.json" in capsys.readouterr().err


def test_missing_export_folder_is_a_clear_error(tmp_path: Path, capsys: pytest.CaptureFixture[str]) -> None:
    assert main(["hil", "run", "--export-dir", str(tmp_path), "--json", str(tmp_path / "x.json")]) == 2
    assert "no c/policy.c" in capsys.readouterr().err


def test_keep_work_keeps_the_temporary_folder_and_names_it(
    export_dir: Path, tmp_path: Path, capsys: pytest.CaptureFixture[str]
) -> None:
    argv = [
        "hil",
        "run",
        "--export-dir",
        str(export_dir),
        "--json",
        str(tmp_path / "h.json"),
        "--node",
        "python",
    ]
    assert main([*argv, "--episodes", "1", "--keep-work"]) == 0
    line = next(x for x in capsys.readouterr().out.splitlines() if x.startswith("kept the node build"))
    kept = Path(line.rsplit(" in ", 1)[1])
    assert (kept / "results.json").is_file()
    shutil.rmtree(kept)
