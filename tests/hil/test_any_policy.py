"""Any exported policy goes over CAN, not only the warehouse robot's: a Pendulum-v1 policy (an SB3 TD3
trained briefly here), its interface derived from the env's spaces, lock-step over the bus equal to the
simulation, on the Python node (fast) and on the C node over vcan (slow)."""

from __future__ import annotations

import json
from pathlib import Path
from typing import Any

import pytest
from stable_baselines3 import TD3

from embedrl.cli import main
from embedrl.hil.sandbox import Guest
from tests.hil.helpers import hil

PENDULUM_STEPS = 200
"""Pendulum-v1's episode length."""


@pytest.fixture(scope="module")
def pendulum_export(tmp_path_factory: pytest.TempPathFactory) -> Path:
    work = tmp_path_factory.mktemp("pendulum")
    model = TD3("MlpPolicy", "Pendulum-v1", seed=0, learning_starts=200, device="cpu",
                policy_kwargs={"net_arch": [32, 32]})  # fmt: skip
    model.learn(600)
    model.save(work / "pendulum.zip")
    out = work / "export"
    assert (
        main(
            [
                "export",
                str(work / "pendulum.zip"),
                "--env",
                "Pendulum-v1",
                "--out",
                str(out),
                "--episodes",
                "0",
            ]
        )
        == 0
    )
    return out


def test_the_export_carries_the_interface_derived_from_the_env(pendulum_export: Path) -> None:
    interface = json.loads((pendulum_export / "interface.json").read_text())
    assert interface["env_id"] == "Pendulum-v1" and interface["max_steps"] == PENDULUM_STEPS
    assert [f["name"] for f in interface["observation"]] == ["obs0", "obs1", "obs2"]
    assert [(f["low"], f["high"]) for f in interface["action"]] == [(-2.0, 2.0)]
    assert interface["safe_action"] == [0.0] and interface["sample_time_s"] == pytest.approx(0.05)


def _check_lock_step(report: dict[str, Any]) -> None:
    assert report["episodes"] == 2 and report["faults"] == 0 and report["steps"] == 2 * PENDULUM_STEPS
    assert report["outcomes_differing_from_simulation"] == []
    assert report["max_action_abs_diff"] <= 1e-5
    for row in report["per_episode"]:  # the same trajectory: returns equal to a millionth or so
        assert row["episode_return"] == pytest.approx(row["simulation_return"], rel=1e-5)
    assert report["frames_tx"] == 2 * report["steps"]  # 3 fields: 2 observation frames a step
    assert report["verdict"] == {"passed": True, "failures": [], "faults_allowed": False}


def test_a_pendulum_policy_in_lock_step_on_the_python_node(pendulum_export: Path, tmp_path: Path) -> None:
    _check_lock_step(hil(None, pendulum_export, tmp_path, "--node", "python", "--episodes", "2"))


@pytest.mark.slow
def test_a_pendulum_policy_in_lock_step_on_the_c_node_over_vcan(
    guest: Guest, pendulum_export: Path, tmp_path: Path
) -> None:
    _check_lock_step(hil(guest, pendulum_export, tmp_path, "--episodes", "2"))
