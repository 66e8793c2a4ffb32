"""``embedrl scope``: one episode against time, and the observation as the node decodes its CAN frames."""

from __future__ import annotations

from pathlib import Path

import numpy as np
import pytest

from embedrl.cli import main
from embedrl.export.contract.layout import rounding_errors
from embedrl.hil import scope
from embedrl.train.potential_field import PotentialFieldController
from embedrl.train.scenarios import SCENARIOS


@pytest.mark.parametrize("scenario", ["static", "moving-shelf"])
def test_the_scope_holds_every_field_and_the_can_rounding_stays_within_half_a_step(scenario: str) -> None:
    episode = scope.record(PotentialFieldController(scenario=scenario), scenario, 2, {})
    fields = len(SCENARIOS[scenario].observation)
    steps = len(episode["actions"])
    assert episode["observations"].shape == episode["decoded"].shape == (steps, fields)
    error = np.abs(episode["decoded"].astype(np.float64) - episode["observations"])
    assert 0 < error.max() <= rounding_errors(SCENARIOS[scenario])["observation"] * (1 + 1e-6)
    assert episode["outcome"] == "success"


def test_the_scope_command_writes_a_picture_or_refuses_in_one_line(
    tmp_path: Path, capsys: pytest.CaptureFixture[str]
) -> None:
    out = tmp_path / "with space" / "scope.png"
    assert main(["scope", "--controller", "potential-field", "--seed", "0", "--out", str(out)]) == 0
    assert out.read_bytes()[:8] == b"\x89PNG\r\n\x1a\n" and "steps, success" in capsys.readouterr().out
    assert main(["scope", "--controller", "potential-field", "--out", str(tmp_path / "scope.gif")]) == 2
    assert "the scope view is a .png file" in capsys.readouterr().err
