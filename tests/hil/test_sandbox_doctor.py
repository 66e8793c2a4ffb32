"""``embedrl hil doctor`` on this machine: every provider booted, self-tested and shut down again.

In a module of its own so that no other test's guest is running while it measures boot times.
"""

from __future__ import annotations

import json
from pathlib import Path

import pytest

import embedrl.hil.sandbox as sandbox
from embedrl.cli import main

pytestmark = pytest.mark.slow
CANDIDATES = sandbox.providers("auto")


def test_the_doctor_checks_every_provider_and_names_the_one_auto_uses(
    tmp_path: Path, capsys: pytest.CaptureFixture[str]
) -> None:
    out = tmp_path / "doctor.json"
    code = main(["hil", "doctor", "--json", str(out)])
    printed = capsys.readouterr().out
    report = json.loads(out.read_text())
    assert report["machine"]["cpu"] and isinstance(report["machine"]["amx"], bool)
    labels = [c["label"] for c in report["providers"]]
    assert labels == [p.label for p in CANDIDATES]
    working = [c for c in report["providers"] if c["works"]]
    assert code == (0 if working else 1)
    assert report["first_working"] == (working[0]["label"] if working else None)
    for c in report["providers"]:
        assert c["reason"]
        assert (c["boot_s"] is not None and c["boot_s"] > 0) == c["works"]
        if c["works"]:
            assert "vcan0 up, AF_CAN frame round trip ok" in c["reason"]
        assert f"{c['label']}  " in printed  # one table row per provider
    assert printed.splitlines()[0].startswith("machine: ")
    assert f"--sandbox auto uses: {report['first_working']}" in printed
