"""`hil run` reads the export's interface once and builds the node from the export's own CAN code; an export
made before exports carried it gets the same generator's code in the run's work folder."""

from __future__ import annotations

import os
import shutil
from pathlib import Path
from typing import Any

import pytest

from embedrl.export.contract.sources import FOLDERS, c_sources
from embedrl.hil.run import check_export, make_node, session_config
from tests.hil.helpers import hil, run_options


def _counting_interface_reads(monkeypatch: pytest.MonkeyPatch) -> list[str]:
    """Every open of a file named interface.json from now on (``read_json`` opens with ``os.open``)."""
    opened: list[str] = []
    real = os.open

    def counting(path: Any, *args: Any, **kwargs: Any) -> int:
        if Path(os.fsdecode(path)).name == "interface.json":
            opened.append(os.fsdecode(path))
        return real(path, *args, **kwargs)

    monkeypatch.setattr(os, "open", counting)
    return opened


def test_a_run_reads_the_interface_once(
    export_dir: Path, tmp_path: Path, monkeypatch: pytest.MonkeyPatch
) -> None:
    opened = _counting_interface_reads(monkeypatch)
    hil(None, export_dir, tmp_path, "--node", "python", "--episodes", "1")
    assert len(opened) == 1, opened


def test_the_c_node_is_checked_and_built_on_one_reading_of_the_interface(
    export_dir: Path, tmp_path: Path, monkeypatch: pytest.MonkeyPatch, capsys: pytest.CaptureFixture[str]
) -> None:
    opened = _counting_interface_reads(monkeypatch)
    options, interface = check_export(run_options(export_dir), [])  # the C regenerated and compared
    binary = make_node(options, interface, tmp_path, {})
    session_config(options, interface, node_binary=str(binary), iface="vcan0", results="r.json")
    assert len(opened) == 1, opened
    assert binary.is_file() and "note:" not in capsys.readouterr().out


def test_an_export_without_its_can_code_gets_it_generated_into_the_work_folder(
    export_dir: Path, tmp_path: Path, capsys: pytest.CaptureFixture[str]
) -> None:
    for folder in FOLDERS:
        shutil.rmtree(export_dir / folder)
    options, interface = check_export(run_options(export_dir), [])  # its C is still the generator's
    assert make_node(options, interface, tmp_path, {}).is_file()
    said = capsys.readouterr().out
    assert f"note: {export_dir} has no can/ (made before exports carried their CAN code)" in said
    for name, text in c_sources(interface).items():
        assert (tmp_path / "can" / name).read_bytes() == text.encode()
    assert not (export_dir / "can").exists()  # the bundle is left as it was
