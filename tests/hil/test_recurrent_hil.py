"""A policy with memory on the bus: RecurrentPPO trained briefly on the partially observed moving shelf,
exported, and driven in lock-step on the C, Python and firmware nodes; the node's state reset at each
episode start (EpisodeStart), in SAFE and at start-up."""

from __future__ import annotations

import json
from pathlib import Path

import cantools
import numpy as np
import pytest

from embedrl.cli import main
from embedrl.export.contract.dbc import database, dbc_text
from embedrl.export.contract.interface_file import load_interface
from embedrl.export.contract.layout import STEP_MODULO, episode_start_id
from embedrl.hil.codec import Codec
from embedrl.hil.sandbox import Guest
from embedrl.train.interface import Interface
from embedrl.train.scenarios import MOVING_SHELF_PARTIAL
from tests.conftest import marks_its_users
from tests.hil.helpers import hil, hil_report

SCENARIO = MOVING_SHELF_PARTIAL.name


@pytest.fixture(scope="module")
@marks_its_users("training")
def recurrent_export(tmp_path_factory: pytest.TempPathFactory) -> Path:
    """recurrent-ppo, preset tuned, 1,500 steps (its warm start clones the teacher over whole episodes)."""
    root = tmp_path_factory.mktemp("recurrent")
    run = root / "run"
    budget = ["--max-steps", "1500", "--eval-every", "100000", "--checkpoint-every", "100000"]
    assert main(["train", "--algo", "recurrent-ppo", "--scenario", SCENARIO, "--seed", "3", *budget,
                 "--out", str(run)]) == 0  # fmt: skip
    out = root / "export"
    assert main(["export", str(run / "model.zip"), "--scenario", SCENARIO, "--episodes", "10",
                 "--out", str(out)]) == 0  # fmt: skip
    return out


def test_the_export_of_a_recurrent_policy_records_its_state_and_the_bus_gets_an_episode_start(
    recurrent_export: Path,
) -> None:
    report = json.loads((recurrent_export / "export_report.json").read_text())
    assert report["closed_loop"]["differing_outcomes"] == 0
    assert report["closed_loop"]["c_trajectory_max_action_diff"] < 1e-5
    interface = load_interface(recurrent_export / "interface.json")
    assert interface.state_size == 2 * 64  # one LSTM layer of 64: h and c
    header = (recurrent_export / "c" / "policy.h").read_text()
    assert "#define POLICY_STATE_DIM 128" in header and "void policy_reset(void);" in header
    db = database(interface, node_id=2)
    message = db.get_message_by_name("EpisodeStart")
    assert message.frame_id == episode_start_id(2) == 0x100 + 2 * 0x20 + 0x1F
    assert [s.name for s in message.signals] == ["Crc", "Counter", "Step"]
    # the frame the simulator sends decodes with the DBC the node is built from
    frame = Codec(interface).encode_episode_start(4100)[0]
    dbc = cantools.database.load_string(dbc_text(interface), database_format="dbc")
    assert isinstance(dbc, cantools.database.can.Database)
    decoded = dbc.decode_message(frame.arbitration_id, bytes(frame.data))
    assert isinstance(decoded, dict) and decoded["Step"] == 4100 % STEP_MODULO


def test_a_policy_without_memory_has_no_episode_start() -> None:
    interface = MOVING_SHELF_PARTIAL
    assert interface.state_size == 0
    assert "EpisodeStart" not in [m.name for m in database(interface).messages]
    assert Codec(interface).encode_episode_start(0) == []
    with_memory = interface.with_state_size(32)
    assert Interface.from_json(json.loads(with_memory.dumps())) == with_memory
    assert "state_size" not in interface.dumps()  # a feed-forward policy's file as before


@pytest.mark.slow
@pytest.mark.parametrize("node", ["c", "python"])
def test_lock_step_episodes_of_a_recurrent_policy_equal_the_simulation(
    guest: Guest, recurrent_export: Path, tmp_path: Path, node: str
) -> None:
    report = hil(guest, recurrent_export, tmp_path, "--node", node, "--episodes", "6")
    assert report["outcomes_differing_from_simulation"] == []
    assert report["max_action_abs_diff"] < 1e-5  # every step of every episode: the state reset at each start
    assert report["max_return_abs_diff"] < 1e-4
    assert report["steps"] > 6 * 5


@pytest.mark.slow
def test_a_recurrent_policy_on_the_firmware_node_equals_the_simulation(
    guest: Guest, recurrent_export: Path, tmp_path: Path
) -> None:
    report = hil(guest, recurrent_export, tmp_path, "--node", "firmware", "--episodes", "2")
    assert report["outcomes_differing_from_simulation"] == [] and report["max_action_abs_diff"] < 1e-5
    assert report["instructions_per_step"]["mean"] > 0


@pytest.mark.slow
def test_a_lost_episode_start_is_caught_by_the_lock_step(
    guest: Guest, recurrent_export: Path, tmp_path: Path, monkeypatch: pytest.MonkeyPatch
) -> None:
    """Without EpisodeStart the node carries the last episode's state into the next: the verdict sees it."""
    monkeypatch.setattr(Codec, "encode_episode_start", lambda self, step: [])
    report = hil_report(guest, recurrent_export, "--node", "python", "--episodes", "3")
    assert not report["verdict"]["passed"]
    assert report["first_divergent_step"] is not None and np.isfinite(report["max_action_abs_diff"])


@pytest.mark.slow
def test_the_deployment_report_of_a_recurrent_export_explains_every_misra_finding(
    recurrent_export: Path, tmp_path: Path, capsys: pytest.CaptureFixture[str]
) -> None:
    out = tmp_path / "report.html"
    assert main(["report", str(recurrent_export), "--out", str(out)]) == 0
    assert "(0 unexplained)" in capsys.readouterr().out and out.is_file()


def test_bench_export_refuses_a_recurrent_export_in_one_line(
    recurrent_export: Path, capsys: pytest.CaptureFixture[str]
) -> None:
    assert main(["bench-export", "--export-dir", str(recurrent_export)]) == 2
    err = capsys.readouterr().err.strip()
    assert "recurrent policy" in err and "\n" not in err


@pytest.mark.slow
def test_the_faults_that_reset_the_state_are_detected_with_a_recurrent_policy(
    guest: Guest, recurrent_export: Path, tmp_path: Path
) -> None:
    """The faults that take the node to SAFE or restart it (and so reset its policy's state): detected, and
    the next episode starts clean (EpisodeStart), its outcome the simulation's."""
    faults = ("delay", "kill-restart", "silent", "corrupt")
    inject = [a for i, kind in enumerate(faults) for a in ("--inject", f"{kind}@{i}:3")]
    argv = ["--episodes", str(len(faults) + 1), "--allow-faults", *inject]
    report = hil(guest, recurrent_export, tmp_path, *argv)
    assert [i["detected"] for i in report["injections"]] == [True] * len(faults)
    last = report["per_episode"][-1]  # after the faults: the node's state reset, the episode the simulation's
    assert last["fault"] is None and last["max_action_abs_diff"] < 1e-5
    assert abs(last["episode_return"] - last["simulation_return"]) < 1e-4
