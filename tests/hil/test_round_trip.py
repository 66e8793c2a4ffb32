"""``embedrl hil bench``: the bus's floor and the lock-step rate, measured in the same guest."""

from __future__ import annotations

from pathlib import Path

import pytest

from embedrl.cli import main
from embedrl.hil.options import RunOptions
from embedrl.hil.round_trip import run_bench
from embedrl.hil.sandbox import Guest


@pytest.mark.slow
def test_the_floor_and_the_lockstep_rate_in_one_guest(guest: Guest, export_dir: Path) -> None:
    result = run_bench(RunOptions(export_dir=export_dir, episodes=2), exchanges=200, guest=guest)
    floor, hil = result["floor"], result["lockstep"]
    assert floor["exchanges"] == 198 and floor["frames_out_per_exchange"] == 3 and floor["per_second"] > 0
    assert hil["steps"] > 0 and hil["faults"] == 0 and hil["per_second"] > 0
    # a HIL step does everything an exchange does and more: it cannot beat the floor by much
    assert result["ratio"] == pytest.approx(hil["per_second"] / floor["per_second"])
    assert 0 < result["ratio"] < 1.2
    assert result["sandbox"] == guest.description


def test_bad_counts_and_a_missing_export_are_refused_in_one_line(
    tmp_path: Path, capsys: pytest.CaptureFixture[str]
) -> None:
    assert main(["hil", "bench", "--export-dir", str(tmp_path), "--exchanges", "0"]) == 2
    assert "--exchanges and --episodes must be at least 1" in capsys.readouterr().err
    out = tmp_path / "b.json"
    assert main(["hil", "bench", "--export-dir", str(tmp_path / "nosuch"), "--json", str(out)]) == 2
    err = capsys.readouterr().err.strip()
    assert len(err.splitlines()) == 1 and "nosuch" in err and not out.exists()
