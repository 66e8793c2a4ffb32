"""Any exported policy goes over CAN, not only the warehouse robot's: a Pendulum-v1 policy (an SB3 TD3
trained briefly here), its interface derived from the env's spaces, lock-step over the bus equal to the
simulation; and an ONNX from elsewhere with no env, its interface from the given ranges, in open loop.
On the Python node (fast) and on the C node over vcan (slow)."""

from __future__ import annotations

import json
from contextlib import nullcontext
from pathlib import Path
from typing import Any

import numpy as np
import onnx
import pytest
from stable_baselines3 import TD3

from embedrl.cli import main
from embedrl.hil.sandbox import Guest
from embedrl.hil.session import OPEN_LOOP_STEPS
from tests.conftest import marks_its_users
from tests.export.helpers import mlp_model
from tests.hil.helpers import hil

PENDULUM_STEPS = 200
"""Pendulum-v1's episode length."""


@pytest.fixture(scope="module")
@marks_its_users("training")
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
    assert report["frames_tx"] == 2 * (
        report["steps"] + report["retries"]
    )  # 3 fields: 2 observation frames a step
    assert report["verdict"] == {"passed": True, "failures": [], "faults_allowed": False}


def test_a_pendulum_policy_in_lock_step_on_the_python_node(pendulum_export: Path, tmp_path: Path) -> None:
    _check_lock_step(hil(None, pendulum_export, tmp_path, "--node", "python", "--episodes", "2"))


@pytest.mark.slow
def test_a_pendulum_policy_in_lock_step_on_the_c_node_over_vcan(
    guest: Guest, pendulum_export: Path, tmp_path: Path
) -> None:
    _check_lock_step(hil(guest, pendulum_export, tmp_path, "--episodes", "2"))


@pytest.fixture(scope="module")
def envless_export(tmp_path_factory: pytest.TempPathFactory) -> Path:
    """An ONNX from elsewhere with no env: 17 observations in [-10, 10], 4 actions in [-1, 1]."""
    work = tmp_path_factory.mktemp("envless")
    model = mlp_model([17, 32, 4], seed=3)
    model.graph.input[0].name, model.graph.node[0].input[0] = "obs", "obs"
    onnx.save(model, work / "walker.onnx")
    (work / "names.json").write_text(json.dumps({"action": ["hip_l", "knee_l", "hip_r", "knee_r"]}))
    out = work / "export"
    argv = ["export", str(work / "walker.onnx"), "--out", str(out), "--obs-range=-10:10", "--act-range=-1:1",
            "--sample-time", "0.02", "--names", str(work / "names.json")]  # fmt: skip
    assert main(argv) == 0
    return out


def test_an_onnx_without_an_env_exports_from_its_ranges(envless_export: Path) -> None:
    interface = json.loads((envless_export / "interface.json").read_text())
    assert interface["env_id"] == "" and interface["sample_time_s"] == 0.02
    assert [(f["low"], f["high"]) for f in interface["observation"]] == [(-10.0, 10.0)] * 17
    assert [f["name"] for f in interface["action"]] == ["hip_l", "knee_l", "hip_r", "knee_r"]
    report = json.loads((envless_export / "export_report.json").read_text())
    assert report["closed_loop"]["skipped"].startswith("no env: the C is verified against onnxruntime")
    assert report["verification"]["c_vs_onnxruntime_max_abs_error"] <= 1e-5
    observations = np.load(envless_export / "test" / "observations.npy")
    assert observations.shape == (10_000, 17) and np.all(np.abs(observations) <= 10)
    assert "POLICY_ACT_KNEE_R 3u" in (envless_export / "c" / "policy.h").read_text()


@pytest.mark.parametrize(
    ("flags", "said"),
    [
        (["--obs-range=-10:10"], "give --obs-range, --act-range and --sample-time together"),
        (
            ["--obs-range=-1:1,-1:1", "--act-range=-1:1", "--sample-time", "0.1"],
            "2 ranges, but the policy observes 17",
        ),
        (["--obs-range=1:-1", "--act-range=-1:1", "--sample-time", "0.1"], "finite with LOW < HIGH"),
        (["--obs-range", "x", "--act-range=-1:1"], "expected LOW:HIGH"),
    ],
)
def test_bad_ranges_are_clear_errors(
    flags: list[str], said: str, envless_export: Path, tmp_path: Path, capsys: pytest.CaptureFixture[str]
) -> None:
    source = envless_export.parent / "walker.onnx"
    with pytest.raises(SystemExit) if said == "expected LOW:HIGH" else nullcontext():
        assert main(["export", str(source), "--out", str(tmp_path / "x"), *flags]) == 2
    assert said in capsys.readouterr().err and not (tmp_path / "x").exists()


def _check_open_loop(report: dict[str, Any]) -> None:
    assert report["open_loop"] is True and report["simulation"] is None
    assert report["episodes"] == 2 and report["faults"] == 0 and report["steps"] == 2 * OPEN_LOOP_STEPS
    assert report["max_action_abs_diff"] <= 1e-5
    assert report["frames_tx"] == 9 * (
        report["steps"] + report["retries"]
    )  # 17 fields: 9 observation frames a step
    # stated: [-10, 10] needs a scale of 2^-15 (half of it the rounding error), [-1, 1] the finest, 2^-18
    assert report["can_rounding_error"] == {"observation": 2**-16, "action": 2**-19}
    assert report["verdict"]["passed"]


def test_a_policy_without_an_env_runs_in_open_loop_on_the_python_node(
    envless_export: Path, tmp_path: Path
) -> None:
    _check_open_loop(hil(None, envless_export, tmp_path, "--node", "python", "--episodes", "2"))


@pytest.mark.slow
def test_a_policy_without_an_env_runs_in_open_loop_on_the_c_node_over_vcan(
    guest: Guest, envless_export: Path, tmp_path: Path
) -> None:
    _check_open_loop(hil(guest, envless_export, tmp_path, "--episodes", "2"))


def _check_fd(report: dict[str, Any]) -> None:
    assert report["open_loop"] is True and report["faults"] == 0 and report["steps"] == OPEN_LOOP_STEPS
    assert report["max_action_abs_diff"] <= 1e-5
    assert (
        report["frames_tx"] == report["steps"] + report["retries"]
    )  # 17 observations in one CAN FD frame a step
    assert report["verdict"]["passed"]


def test_can_fd_carries_the_observation_in_one_frame_on_the_python_node(
    envless_export: Path, tmp_path: Path
) -> None:
    _check_fd(hil(None, envless_export, tmp_path, "--node", "python", "--episodes", "1", "--fd"))


@pytest.mark.slow
def test_can_fd_over_vcan_with_the_c_node(guest: Guest, envless_export: Path, tmp_path: Path) -> None:
    log = tmp_path / "frames.log"
    _check_fd(hil(guest, envless_export, tmp_path, "--episodes", "1", "--fd", "--log", str(log)))
    sent = [line for line in log.read_text().splitlines() if line.endswith(" T")]
    assert all("##" in line for line in sent)  # candump's mark of a CAN FD frame
