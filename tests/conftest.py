"""Shared fixtures and the suite's tiers.

- ``env``: a fresh registered environment per test.
- ``exported``: ``embedrl export`` run once per session for each (source content, flags), shared by every test
  that reads the same export; a test that changes an export copies it first (``shutil.copytree``).
- Tiers: markers set by the fixtures a test uses (``@marks_its_users``): ``sandbox`` (a CAN sandbox guest),
  ``qemu`` (a QEMU machine: the x86 sandbox guest or Cortex-M firmware), ``training`` (trains a policy),
  ``slow`` (minutes of work, e.g. many exports); a test that does such a thing itself carries the marker.
  ``make test-fast`` deselects all four; ``make test`` runs everything.
- Side by side: ``make test`` runs the suite on two pytest-xdist workers, a test file per worker at a time
  (``--dist loadfile``: a file's module and session fixtures are made once per worker; the files that use the
  QEMU guest go to one worker together, :data:`ONE_QEMU_GUEST`), the longest files first
  (:data:`LONGEST_FIRST`); each worker has its own temporary folder, so a test that counts the
  temporary folders a run leaves sees only its own worker's.
- SIGTERM stops the session as Ctrl-C does (fixtures torn down, guests closed), also when it arrives while
  a test runs ``embedrl.cli.main`` in-process, whose own handler would otherwise turn it into one failed
  test and let the session run on.
"""

from __future__ import annotations

import contextlib
import os
import shutil
import signal
import tempfile
from collections.abc import Callable, Generator, Iterator
from pathlib import Path
from types import FrameType
from typing import TypeVar

import gymnasium as gym
import numpy as np
import pytest

import embedrl.cli
from embedrl import train
from embedrl.cli import main
from embedrl.common import sha256

TIERS = ("slow", "sandbox", "qemu", "training")
"""The markers a fixture may set on the tests that use it (registered in pyproject.toml)."""
Fixture = TypeVar("Fixture", bound=Callable[..., object])
LONGEST_FIRST = (
    "tests/test_readme.py",
    "tests/hil/test_paths_matrix.py",
    "tests/hil/test_hil_vcan.py",
    "tests/test_training.py",
    "tests/test_tune.py",
    "tests/hil/test_sandbox_providers.py",
    "tests/hil/test_firmware.py",
)
"""Test files that take minutes, collected first so that side by side they start first, not last."""
ONE_QEMU_GUEST = (
    "tests/hil/test_paths_matrix.py",
    "tests/hil/test_hil_vcan.py",
    "tests/hil/test_sandbox_providers.py",
)
"""The test files that use the session's QEMU guest (``qemu_guest``): side by side, one work unit, so that one
worker boots one guest for all of them (a boot and the guest's imports take minutes of a core)."""


def marks_its_users(*markers: str) -> Callable[[Fixture], Fixture]:
    """Marks every test that uses the decorated fixture, directly or through other fixtures, with
    ``markers`` (among ``TIERS``). Goes below ``@pytest.fixture``."""
    assert set(markers) <= set(TIERS), markers

    def mark(fixture: Fixture) -> Fixture:
        fixture.tier_markers = markers  # type: ignore[attr-defined]
        return fixture

    return mark


Exported = Callable[..., Path]


@pytest.fixture
def env() -> Iterator[gym.Env[np.ndarray, np.ndarray]]:
    e = gym.make(train.ENV_ID)
    yield e
    e.close()


@pytest.fixture(scope="session")
def exported(tmp_path_factory: pytest.TempPathFactory) -> Iterator[Exported]:
    """``exported(source, *flags)``: the folder of ``embedrl export source --out FOLDER *flags``, run once per
    session for each source content (its SHA-256) and flags. Read it; copy it before changing anything."""
    folders: dict[tuple[str, tuple[str, ...]], Path] = {}
    contents: dict[Path, dict[str, str]] = {}

    def export(source: Path, *flags: str) -> Path:
        key = (sha256(source), flags)
        if key not in folders:
            out = tmp_path_factory.mktemp("exported") / "export"
            assert main(["export", str(source), "--out", str(out), *flags]) == 0, (source, flags)
            folders[key], contents[out] = out, _digests(out)
        return folders[key]

    yield export
    changed = {
        str(out): sorted(name for name in {*before, *now} if before.get(name) != now.get(name))
        for out, before in contents.items()
        if (now := _digests(out)) != before
    }
    assert not changed, f"a test changed a shared export instead of a copy of it: {changed}"


def _digests(folder: Path) -> dict[str, str]:
    """Every file under ``folder`` -> its SHA-256."""
    return {str(p.relative_to(folder)): sha256(p) for p in sorted(folder.rglob("*")) if p.is_file()}


def pytest_addoption(parser: pytest.Parser) -> None:
    parser.addoption(
        "--regen-golden",
        action="store_true",
        help="rewrite the generated-code golden files instead of comparing with them",
    )


def _longest_first(item: pytest.Item) -> int:
    path = item.nodeid.split("::", 1)[0]
    return LONGEST_FIRST.index(path) if path in LONGEST_FIRST else len(LONGEST_FIRST)


def pytest_collection_modifyitems(items: list[pytest.Item]) -> None:
    items.sort(key=_longest_first)  # stable: the order within a file is kept
    for item in items:
        if not isinstance(item, pytest.Function):
            continue
        path = item.nodeid.split("::", 1)[0]
        if "qemu_guest" in item.fixturenames and path not in ONE_QEMU_GUEST:
            raise pytest.UsageError(f"{path} uses qemu_guest: add it to ONE_QEMU_GUEST (tests/conftest.py)")
        for definitions in item._fixtureinfo.name2fixturedefs.values():  # the fixtures it uses, transitively
            for definition in definitions:
                for marker in getattr(definition.func, "tier_markers", ()):
                    item.add_marker(marker)


def pytest_xdist_make_scheduler(config: pytest.Config, log: object) -> object:
    """``--dist loadfile`` with the files of :data:`ONE_QEMU_GUEST` as one work unit."""
    if config.getvalue("dist") != "loadfile":
        return None
    from xdist.scheduler import LoadFileScheduling

    class OneQemuGuest(LoadFileScheduling):  # type: ignore[misc]  # xdist has no type information
        def _split_scope(self, nodeid: str) -> str:
            path = super()._split_scope(nodeid)
            return ONE_QEMU_GUEST[0] if path in ONE_QEMU_GUEST else path

    return OneQemuGuest(config, log)


class _Stopped:
    """The stop signal that arrived while a test ran ``embedrl.cli.main`` in-process, if any."""

    signum: int | None = None


def _raise_stop(signum: int, frame: FrameType | None) -> None:
    raise embedrl.cli.Terminated if signum == signal.SIGTERM else KeyboardInterrupt


def _stop_workers_too(signum: int, frame: FrameType | None) -> None:
    """The xdist controller's stop: its workers (its only children) get the signal at once, then it stops;
    otherwise it would wait for each worker's current test before ending it."""
    for task in Path("/proc/self/task").iterdir():
        for pid in (task / "children").read_text().split():
            with contextlib.suppress(ProcessLookupError):  # ended meanwhile
                os.kill(int(pid), signum)
    _raise_stop(signum, frame)


def _recording_stop(command_stop: Callable[[int, FrameType | None], None]) -> Callable[..., None]:
    def stop(signum: int, frame: FrameType | None) -> None:
        _Stopped.signum = signum
        command_stop(signum, frame)

    return stop


class _Worker:
    """This xdist worker's own temporary folder (``None`` outside a worker)."""

    folder: Path | None = None


def pytest_configure(config: pytest.Config) -> None:
    worker = os.environ.get("PYTEST_XDIST_WORKER")
    if worker:
        _Worker.folder = Path(tempfile.mkdtemp(prefix=f"tests-{worker}-"))
        os.environ["TMPDIR"] = str(_Worker.folder)  # for the commands the tests run, too
        tempfile.tempdir = None  # tempfile reads TMPDIR again
    controller = not worker and (getattr(config.option, "numprocesses", None) or 0) > 0
    stop = _stop_workers_too if controller else _raise_stop
    signal.signal(signal.SIGTERM, stop)  # teardown runs (guests closed) instead of a hard exit
    embedrl.cli._stop = _recording_stop(embedrl.cli._stop)


def pytest_unconfigure(config: pytest.Config) -> None:
    if _Worker.folder is not None:
        shutil.rmtree(_Worker.folder, ignore_errors=True)


@pytest.hookimpl(wrapper=True)
def pytest_runtest_protocol(item: pytest.Item) -> Generator[None, object, object]:
    result = yield
    if _Stopped.signum is not None:  # the command under test swallowed it: stop here as pytest would
        signum, _Stopped.signum = _Stopped.signum, None
        _raise_stop(signum, None)
    return result
