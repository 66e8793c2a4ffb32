"""HIL fixtures: the exported example policy, and the CAN sandbox guests shared by a whole test session.

A guest serves any number of HIL runs, so the suite boots each sandbox once per session (and worker)
instead of once per test: ``guest`` is the one ``--sandbox auto`` picks (``EMBEDRL_TEST_SANDBOX``, default
``auto``, picks another, e.g. ``qemu`` to run the whole HIL suite under QEMU), ``qemu_guest`` the QEMU
machine that the QEMU rows of the paths matrix, the QEMU provider's episode and the emulated default timing
share.
"""

from __future__ import annotations

import os
import shutil
from collections.abc import Iterator
from pathlib import Path

import pytest

import embedrl.hil.sandbox as sandbox
from embedrl.hil.sandbox import Guest
from embedrl.hil.sandbox.qemu import QemuProvider
from tests.conftest import Exported, marks_its_users
from tests.hil.helpers import boot_or_skip

SHIPPED_TD3 = Path(__file__).resolve().parents[2] / "policies" / "static" / "td3.zip"


@pytest.fixture
def export_dir(exported: Exported, tmp_path_factory: pytest.TempPathFactory) -> Path:
    """The shipped TD3 policy (199/200 successes on unseen seeds), exported without the closed loop: the
    session's export, copied for each test (``hil run --json`` adds its report to the export's chain)."""
    return _copy(exported(SHIPPED_TD3, "--episodes", "0"), tmp_path_factory)


@pytest.fixture
def safe_export_dir(exported: Exported, tmp_path_factory: pytest.TempPathFactory) -> Path:
    """The same policy exported with ``--safe-action 0.1,0``, copied for each test."""
    return _copy(exported(SHIPPED_TD3, "--episodes", "0", "--safe-action", "0.1,0"), tmp_path_factory)


def _copy(export: Path, tmp_path_factory: pytest.TempPathFactory) -> Path:
    copy = tmp_path_factory.mktemp("export") / "export"
    shutil.copytree(export, copy)
    return copy


@pytest.fixture(scope="session")
@marks_its_users("sandbox")
def guest(tmp_path_factory: pytest.TempPathFactory) -> Iterator[Guest]:
    """What ``--sandbox auto`` (or ``EMBEDRL_TEST_SANDBOX``) picks on this machine, booted once."""
    mode = os.environ.get("EMBEDRL_TEST_SANDBOX", "auto")
    with sandbox.opened(mode, tmp_path_factory.mktemp("sandbox")) as booted:
        yield booted


@pytest.fixture(scope="session")
@marks_its_users("sandbox", "qemu")
def qemu_guest(tmp_path_factory: pytest.TempPathFactory) -> Iterator[Guest]:
    """The ``qemu`` provider booted once (self-tested, as ``--sandbox qemu`` boots it); skipped, saying why,
    only where QEMU cannot run here (a failure where ``EMBEDRL_REQUIRE_SANDBOXES`` names ``qemu``)."""
    with boot_or_skip(QemuProvider(), tmp_path_factory.mktemp("qemu")) as booted:
        yield booted
