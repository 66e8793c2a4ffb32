"""System tools found where Debian puts them, whatever PATH says, and ``hil doctor``'s progress while a
sandbox boots.

A non-root user's PATH often lacks /usr/sbin and /sbin, where kmod's ``insmod`` and ``modprobe`` live: the
UML provider must still find them (it once fell back to minutes of QEMU emulation instead).
"""

from __future__ import annotations

import shutil
import time
from pathlib import Path

import pytest

import embedrl.hil.sandbox as sandbox
from embedrl.common import SYSTEM_TOOL_DIRS, system_tool
from embedrl.hil import doctor
from embedrl.hil.sandbox import Guest, Provider, SandboxError
from embedrl.hil.sandbox.uml import uml_providers
from tests.hil.helpers import boot_or_skip

NO_SBIN = "/usr/bin:/bin"
"""A user's PATH without the system folders."""


@pytest.fixture
def no_sbin(monkeypatch: pytest.MonkeyPatch) -> None:
    monkeypatch.setenv("PATH", NO_SBIN)
    if shutil.which("insmod") is not None:
        pytest.skip(f"insmod is in {NO_SBIN} on this machine: nothing to find elsewhere")


def test_system_tools_are_found_in_the_system_folders_when_path_lacks_them(no_sbin: None) -> None:
    found = system_tool("insmod")
    if found is None:
        pytest.skip("kmod (insmod) is not installed here")
    assert str(Path(found).parent) in SYSTEM_TOOL_DIRS and Path(found).name == "insmod"
    assert system_tool("modprobe") is not None and system_tool("ip") is not None
    assert system_tool("embedrl-no-such-tool") is None
    for provider in uml_providers():  # the tools no longer count as missing
        assert "insmod" not in (provider.missing() or "")


@pytest.mark.sandbox
def test_a_uml_guest_boots_and_passes_its_self_test_with_a_path_without_sbin(
    no_sbin: None, tmp_path: Path
) -> None:
    """The guest's set-up loads the CAN modules with insmod and brings vcan0 up with ip."""
    provider = uml_providers()[-1]  # the last one: a cached kernel when there is one, else the package's
    guest = boot_or_skip(provider, tmp_path)
    try:
        assert guest.boot_s > 0 and guest.iface == "vcan0"
    finally:
        guest.close()


class _SlowToBoot(Provider):
    """Boots for ``seconds``, then fails as a dead guest would."""

    name = "uml"
    label = "slow (test)"

    def __init__(self, seconds: float) -> None:
        self.seconds = seconds

    def missing(self) -> str | None:
        return None

    def boot(self, workdir: Path) -> Guest:
        time.sleep(self.seconds)
        raise SandboxError("died while booting (test)")


def test_the_doctor_says_a_provider_is_still_booting(monkeypatch: pytest.MonkeyPatch) -> None:
    monkeypatch.setattr(sandbox, "providers", lambda mode: [_SlowToBoot(0.5)])
    said: list[str] = []
    report = doctor.doctor(say=said.append, mode="uml", progress_s=0.1)
    ticks = [line for line in said if "slow (test): still booting or self-testing" in line]
    assert said[1] == "checking slow (test) ..." and 3 <= len(ticks) <= 5, said
    assert said.index(ticks[0]) == 2 and len(said) == 2 + len(ticks)  # between its start and its row
    assert report["providers"][0]["works"] is False and report["first_working"] is None


class _Named(Provider):
    """A provider that only has a name: ``sandbox.check`` is replaced in the test that uses it."""

    name = "uml"

    def __init__(self, label: str) -> None:
        self.label = label

    def missing(self) -> str | None:
        return None

    def boot(self, workdir: Path) -> Guest:
        raise AssertionError("not booted in this test")


@pytest.mark.parametrize("every", [False, True])
def test_the_doctor_stops_at_the_first_provider_that_works_unless_told_all(
    monkeypatch: pytest.MonkeyPatch, every: bool
) -> None:
    from embedrl.hil.sandbox import ProviderCheck

    works = {"a": False, "b": True, "c": True}
    monkeypatch.setattr(sandbox, "providers", lambda mode: [_Named(label) for label in works])
    monkeypatch.setattr(
        sandbox,
        "check",
        lambda p, w: ProviderCheck(
            p.name, p.label, works[p.label], 1.0 if works[p.label] else None, "ok" if works[p.label] else "no"
        ),
    )
    said: list[str] = []
    report = doctor.doctor(say=said.append, every=every)
    doctor.print_table(report, said.append)
    assert [c["label"] for c in report["providers"]] == (["a", "b", "c"] if every else ["a", "b"])
    assert report["not_checked"] == ([] if every else ["c"]) and report["first_working"] == "b"
    assert any(line.startswith("c: not checked") for line in said) != every
