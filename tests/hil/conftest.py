"""HIL fixtures: the exported example policy, and a CAN sandbox guest shared by a whole test session.

A guest serves any number of HIL runs, so the suite boots each sandbox once instead of once per test.
``EMBEDRL_TEST_SANDBOX`` (default ``auto``) picks the sandbox of the shared guest, e.g. ``qemu`` to run
the whole HIL suite under QEMU.
"""

from __future__ import annotations

import os
import subprocess
import sys
from collections.abc import Iterator
from pathlib import Path

import pytest

import embedrl.hil.sandbox as sandbox
from embedrl.cli import main
from embedrl.hil.sandbox import Guest


@pytest.fixture(scope="session")
def export_dir(tmp_path_factory: pytest.TempPathFactory) -> Path:
    """The example TD3 actor (imitating the potential-field controller, so its episodes succeed), exported."""
    root = tmp_path_factory.mktemp("hil")
    subprocess.run(
        [sys.executable, "-m", "embedrl.export.example", str(root / "td3.zip")],
        check=True,
        capture_output=True,
    )
    assert main(["export", str(root / "td3.zip"), "--out", str(root / "export"), "--episodes", "0"]) == 0
    return root / "export"


@pytest.fixture(scope="session")
def guest(tmp_path_factory: pytest.TempPathFactory) -> Iterator[Guest]:
    """What ``--sandbox auto`` (or ``EMBEDRL_TEST_SANDBOX``) picks on this machine, booted once."""
    mode = os.environ.get("EMBEDRL_TEST_SANDBOX", "auto")
    with sandbox.opened(mode, tmp_path_factory.mktemp("sandbox")) as booted:
        yield booted
