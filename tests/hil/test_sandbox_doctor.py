"""``embedrl hil doctor`` on this machine: providers booted, self-tested and shut down again.

The test checks the host and every UML kernel (seconds); the QEMU guest's boot and self-test, the same
code path, are proven by its own lock-step test in test_sandbox_providers.py. In a module of its own so
that no other test's guest is running while it measures boot times.
"""

from __future__ import annotations

import json
from pathlib import Path

import pytest

import embedrl.hil.sandbox as sandbox
from embedrl.cli import main
from tests.hil.helpers import REQUIRED

pytestmark = pytest.mark.slow
CANDIDATES = [p for p in sandbox.providers("auto") if p.name != "qemu"]


def test_the_doctor_checks_each_provider_and_names_the_one_to_use(
    tmp_path: Path, capsys: pytest.CaptureFixture[str]
) -> None:
    rows = []
    for mode in ("host", "uml"):
        out = tmp_path / f"doctor-{mode}.json"
        code = main(["hil", "doctor", "--json", str(out), "--sandbox", mode])
        printed = capsys.readouterr().out
        report = json.loads(out.read_text())
        assert (
            report["mode"] == mode and report["machine"]["cpu"] and isinstance(report["machine"]["amx"], bool)
        )
        assert all(c["provider"] == mode for c in report["providers"])
        working = [c for c in report["providers"] if c["works"]]
        assert code == (0 if working else 1)
        assert report["first_working"] == (working[0]["label"] if working else None)
        assert printed.splitlines()[0].startswith("machine: ")
        if working:
            assert f"--sandbox {mode} uses: {report['first_working']}" in printed
        for c in report["providers"]:
            assert c["reason"] and f"{c['label']}  " in printed  # one table row per provider
            assert (c["boot_s"] is not None and c["boot_s"] > 0) == c["works"]
            if c["works"]:
                assert "vcan0 up, AF_CAN frame round trip ok" in c["reason"]
        rows += report["providers"]
    assert [c["label"] for c in rows] == [p.label for p in CANDIDATES]
    if "uml" in REQUIRED:  # CI: a UML kernel must work on this CPU (make deps caches one that does)
        assert any(c["works"] for c in rows if c["provider"] == "uml")
