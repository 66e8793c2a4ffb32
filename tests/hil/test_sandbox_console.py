"""A guest that dies says why; ``auto`` falls back to the next provider and says why it skipped.

Fast: no kernel is booted. The guests here are :class:`VmGuest` objects whose "virtual machine" is a
shell command replaying a recorded console log (``consoles/``, see its README), so the code path from
a dying process to the user's message is the real one.
"""

from __future__ import annotations

import shlex
import time
from collections.abc import Iterator
from pathlib import Path

import pytest

import embedrl.hil.sandbox as sandbox
from embedrl.hil.errors import HilError
from embedrl.hil.sandbox.base import Guest, JobResult, Provider, SandboxError, VmGuest
from embedrl.hil.sandbox.console import diagnose

CONSOLES = Path(__file__).parent / "consoles"

# file, cause, a phrase of the explanation, a line the evidence must quote
RECORDED = [
    ("uml61_amx_fpu_panic.log", "cpu-fpu", "cannot run on this CPU", "ptrace set fp regs failed, errno = 14"),
    ("uml_no_init_panic.log", "kernel-panic", "panicked", "Kernel panic - not syncing: Requested init"),
    ("uml_glibc_too_old.log", "glibc", "newer glibc", "version `GLIBC_2.38' not found"),
    ("uml_missing_modules.log", "missing-modules", "lacks the CAN modules", "embedrl: no vcan0"),
    ("uml_out_of_memory.log", "out-of-memory", "ran out of memory", "Out of memory: Killed process"),
    ("qemu_kvm_msr.log", "kvm", "with KVM", "failed to set MSR 0x10a"),
]


def _replay(log: str, then: str = "exit 1") -> list[str]:
    """A command that prints a recorded console, then behaves as ``then`` (a dead or hung guest)."""
    return ["sh", "-c", f"cat {shlex.quote(str(CONSOLES / log))}; {then}"]


@pytest.mark.parametrize(("log", "cause", "phrase", "evidence"), RECORDED)
def test_each_recorded_failure_is_named(log: str, cause: str, phrase: str, evidence: str) -> None:
    found = diagnose((CONSOLES / log).read_text())
    assert found.cause == cause
    assert phrase in found.explanation
    assert any(evidence in line for line in found.evidence)
    assert len(found.evidence) <= 4


def test_the_fpu_incompatibility_wins_over_the_panic_it_causes() -> None:
    text = (CONSOLES / "uml61_amx_fpu_panic.log").read_text()
    assert "Kernel panic" in text
    found = diagnose(text)
    assert found.cause == "cpu-fpu" and "UML >= 7.2" in found.explanation


def test_a_hung_boot_is_a_timeout_quoting_the_last_lines() -> None:
    found = diagnose((CONSOLES / "uml_boot_timeout.log").read_text(), timed_out=True, timeout_s=6)
    assert found.cause == "timeout" and "within 6 s" in found.explanation
    assert found.evidence[-1] == "embedrl: (test) this init never gets ready"


def test_an_unknown_death_still_quotes_the_log() -> None:
    found = diagnose("booting\nsomething odd happened\n")
    assert found.cause == "unknown" and found.evidence == ("booting", "something odd happened")
    assert diagnose("").cause == "no-output"


@pytest.mark.parametrize(("log", "cause", "phrase", "evidence"), RECORDED)
def test_a_guest_dying_while_booting_raises_the_diagnosis(
    log: str, cause: str, phrase: str, evidence: str, tmp_path: Path
) -> None:
    with pytest.raises(SandboxError) as caught:
        VmGuest("uml", "uml: test kernel", _replay(log), tmp_path, "", "true", boot_timeout_s=30)
    assert caught.value.diagnosis is not None and caught.value.diagnosis.cause == cause
    message = str(caught.value)
    assert "uml: test kernel exited while booting (exit status 1)" in message
    assert phrase in message and evidence in message
    assert "ended without a result" not in message


def test_a_guest_that_never_gets_ready_is_stopped_at_the_boot_timeout(tmp_path: Path) -> None:
    start = time.monotonic()
    with pytest.raises(SandboxError, match="no result within 1 s") as caught:
        VmGuest("uml", "uml", _replay("uml_boot_timeout.log", "exec sleep 60"), tmp_path, "", "true", 1.0)
    assert time.monotonic() - start < 10  # the hung guest was killed, not waited for
    assert caught.value.diagnosis is not None and caught.value.diagnosis.cause == "timeout"
    assert "this init never gets ready" in str(caught.value)


@pytest.fixture
def shell_guest(tmp_path: Path) -> Iterator[VmGuest]:
    """The guest script itself run by the host's shell: the job protocol without a kernel."""
    guest = VmGuest("test", "shell", ["sh", str(tmp_path / "guest.sh")], tmp_path, "", "true", 30)
    yield guest
    guest.close()


def test_one_guest_runs_many_jobs_with_status_output_and_cwd(shell_guest: VmGuest, tmp_path: Path) -> None:
    first = shell_guest.run(["sh", "-c", "pwd; echo to-stderr >&2; exit 3"], tmp_path, timeout_s=30)
    assert first.status == 3
    assert first.output.splitlines() == [str(tmp_path), "to-stderr"]
    second = shell_guest.run(["echo", "a b", "$HOME"], Path("/"), timeout_s=30)  # arguments are quoted
    assert second == JobResult(0, "a b $HOME\n")
    assert shell_guest.scratch().parent == tmp_path  # writable from inside the guest
    shell_guest.close()
    assert shell_guest.process.returncode == 0  # stopped by the host's request, not killed
    with pytest.raises(SandboxError, match="shut down"):
        shell_guest.run(["true"], tmp_path, timeout_s=5)


def test_a_job_that_outlives_its_timeout_is_an_error_with_its_output(
    shell_guest: VmGuest, tmp_path: Path
) -> None:
    with pytest.raises(SandboxError, match=r"no result within 1 s .*started"):
        shell_guest.run(["sh", "-c", "echo started; sleep 30"], tmp_path, timeout_s=1)


def test_a_guest_dying_during_a_job_is_diagnosed(tmp_path: Path) -> None:
    # The "kernel" prints a panic and exits as soon as the first job arrives.
    script = f"touch {tmp_path}/queue/ready; while [ ! -e {tmp_path}/queue/job-1.sh ]; do sleep 0.05; done; "
    command = ["sh", "-c", script + f"cat {CONSOLES / 'uml_no_init_panic.log'}; exit 134"]
    guest = VmGuest("uml", "uml: test", command, tmp_path, "", "true", 30)
    with pytest.raises(
        SandboxError, match=r"died while running `python -m embedrl.hil.session x` .*panicked"
    ):
        guest.run(["python", "-m", "embedrl.hil.session", "x"], tmp_path, timeout_s=30)


class FakeGuest(Guest):
    def __init__(self, name: str, probe_status: int = 0) -> None:
        self.provider, self.description, self.boot_s = name, f"{name}: fake", 0.5
        self.probe_status = probe_status
        self.closed = False

    def run(self, argv: list[str], cwd: Path, timeout_s: float) -> JobResult:
        return JobResult(self.probe_status, "no AF_CAN socket" if self.probe_status else "AF_CAN ok")

    def close(self) -> None:
        self.closed = True


class FakeProvider(Provider):
    """``missing``: a reason; ``log``: boot dies replaying that console; else boots a FakeGuest."""

    def __init__(self, name: str, label: str, missing: str | None = None, log: str | None = None) -> None:
        self.name, self.label = name, label
        self.reason, self.log = missing, log
        self.guest: FakeGuest | None = None

    def missing(self) -> str | None:
        return self.reason

    def boot(self, workdir: Path) -> Guest:
        if self.log:
            VmGuest(self.name, self.label, _replay(self.log), workdir, "", "true", 30)
        self.guest = FakeGuest(self.name, probe_status=1 if self.label.endswith("broken") else 0)
        return self.guest


def _candidates(monkeypatch: pytest.MonkeyPatch, *found: Provider) -> None:
    monkeypatch.setattr(sandbox, "providers", lambda mode: [p for p in found if mode in ("auto", p.name)])


def test_auto_falls_back_past_a_dead_kernel_and_says_why(
    monkeypatch: pytest.MonkeyPatch, tmp_path: Path
) -> None:
    _candidates(
        monkeypatch,
        FakeProvider("host", "host", missing="no vcan0 on this host and it cannot be created"),
        FakeProvider("uml", "uml (Debian 6.1)", log="uml61_amx_fpu_panic.log"),
        FakeProvider("uml", "uml (7.2um1, cached)"),
        FakeProvider("qemu", "qemu"),
    )
    said: list[str] = []
    guest = sandbox.select("auto", tmp_path, said.append)
    assert guest.description == "uml: fake"
    assert said[0] == "sandbox: uml: fake (self-test passed, boot 0.5 s)"
    assert said[1] == "  skipped host: no vcan0 on this host and it cannot be created"
    assert said[2].startswith("  skipped uml (Debian 6.1): uml (Debian 6.1) exited while booting")
    assert "cannot run on this CPU" in said[2] and "ptrace set fp regs failed" in said[2]


def test_a_provider_that_boots_but_fails_its_self_test_is_skipped_and_shut_down(
    monkeypatch: pytest.MonkeyPatch, tmp_path: Path
) -> None:
    broken = FakeProvider("uml", "uml broken")
    _candidates(monkeypatch, broken, FakeProvider("qemu", "qemu"))
    said: list[str] = []
    assert sandbox.select("auto", tmp_path, said.append).provider == "qemu"
    assert broken.guest is not None and broken.guest.closed
    assert "self-test failed (status 1): no AF_CAN socket" in said[1]


def test_a_forced_provider_that_fails_is_an_error_naming_every_reason(
    monkeypatch: pytest.MonkeyPatch, tmp_path: Path
) -> None:
    _candidates(
        monkeypatch,
        FakeProvider("host", "host"),
        FakeProvider("uml", "uml (Debian 6.1)", log="uml61_amx_fpu_panic.log"),
        FakeProvider("uml", "uml (7.2um1, cached)", missing="no User-Mode Linux kernel at /x"),
    )
    with pytest.raises(SandboxError) as caught:
        sandbox.select("uml", tmp_path, lambda line: None)
    message = str(caught.value)
    assert message.startswith("no CAN sandbox works on this machine (--sandbox uml): uml (Debian 6.1): ")
    assert "cannot run on this CPU" in message and "no User-Mode Linux kernel at /x" in message
    assert "embedrl hil doctor" in message


def test_the_real_candidates_follow_the_documented_order() -> None:
    found = sandbox.providers("auto")
    names = [p.name for p in found]
    assert names[0] == "host" and names[-1] == "qemu" and set(names[1:-1]) == {"uml"}
    assert [p.name for p in sandbox.providers("qemu")] == ["qemu"]
    with pytest.raises(HilError, match="unknown sandbox 'kvm'; use one of auto, host, uml, qemu"):
        sandbox.providers("kvm")
