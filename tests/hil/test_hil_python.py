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
