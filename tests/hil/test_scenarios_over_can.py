"""The study's other scenarios over CAN with their shipped policies: the moving shelf (a larger observation,
more frames a step) and two robots with one node per robot on one bus, in lock-step equal to the
simulation; a killed node takes only its own robot into the fault path. On the Python nodes over
python-can's virtual bus (fast) and on the C nodes over vcan (slow)."""

from __future__ import annotations

from pathlib import Path
from typing import Any

import pytest

from embedrl.cli import main
from embedrl.export.contract import layout as can_layout
from embedrl.hil.sandbox import Guest
from embedrl.train.scenarios import MOVING_SHELF, STATIC, TWO_ROBOTS
from tests.hil.helpers import hil

POLICIES = Path(__file__).resolve().parents[2] / "policies"


def _export(tmp_path_factory: pytest.TempPathFactory, scenario: str) -> Path:
    out = tmp_path_factory.mktemp(scenario) / "export"
    args = ["export", str(POLICIES / scenario / "td3.zip"), "--scenario", scenario, "--out", str(out)]
    assert main([*args, "--episodes", "0"]) == 0
    return out


@pytest.fixture(scope="module")
def moving_shelf_export(tmp_path_factory: pytest.TempPathFactory) -> Path:
    return _export(tmp_path_factory, "moving-shelf")


@pytest.fixture(scope="module")
def two_robots_export(tmp_path_factory: pytest.TempPathFactory) -> Path:
    return _export(tmp_path_factory, "two-robots")


def _frames_per_step(interface: Any) -> int:
    layout = can_layout.layout(interface)
    return len(layout.observation)


def _check_moving_shelf(report: dict[str, Any], episodes: int) -> None:
    assert report["episodes"] == episodes and report["faults"] == 0
    assert report["outcomes_differing_from_simulation"] == []
    assert report["max_action_abs_diff"] <= 1e-5
    for row in report["per_episode"]:
        assert row["episode_return"] == pytest.approx(row["simulation_return"], abs=1e-3)
    frames = _frames_per_step(MOVING_SHELF)
    assert frames > _frames_per_step(STATIC)  # 9 values need more frames
    assert report["frames_tx"] == frames * (report["steps"] + report["retries"])
    assert report["verdict"]["passed"], report["verdict"]


def test_moving_shelf_policy_in_lock_step_on_the_python_node(
    moving_shelf_export: Path, tmp_path: Path
) -> None:
    _check_moving_shelf(hil(None, moving_shelf_export, tmp_path, "--node", "python", "--episodes", "3"), 3)


@pytest.mark.slow
def test_moving_shelf_policy_in_lock_step_on_the_c_node_over_vcan(
    guest: Guest, moving_shelf_export: Path, tmp_path: Path
) -> None:
    _check_moving_shelf(hil(guest, moving_shelf_export, tmp_path, "--episodes", "10"), 10)


def _check_two_robots(report: dict[str, Any], episodes: int, log: Path) -> None:
    assert report["episodes"] == 2 * episodes and report["faults"] == 0
    # One row per robot and episode, both robots in the same episode (the same seed).
    assert [(r["seed"], r["node"]) for r in report["per_episode"]] == [
        (i, k) for i in range(episodes) for k in range(2)
    ]
    assert report["outcomes_differing_from_simulation"] == []
    assert report["two_robots"]["hil_both_through"] == report["two_robots"]["simulation_both_through"]
    assert report["two_robots"]["episodes"] == episodes
    assert report["max_action_abs_diff"] <= 1e-5
    for row in report["per_episode"]:
        assert row["episode_return"] == pytest.approx(row["simulation_return"], abs=1e-3)
    assert [n["node_id"] for n in report["nodes"]] == [0, 1]
    assert all(n["diag"]["stale_steps"] == 0 and n["status"]["frames_ok"] > 0 for n in report["nodes"])
    # Each node received only its own robot's frames: its own IDs, nothing else on its filter.
    ids = {line.split()[2].split("#")[0] for line in log.read_text().splitlines()}
    expected = set()
    for k in range(2):
        layout = can_layout.layout(TWO_ROBOTS, k)
        expected |= {f"{i:03X}" for _, i, _ in (*layout.observation, *layout.action)}
        expected |= {f"{can_layout.status_id(k):03X}", f"{can_layout.status_id(k) + 1:03X}"}
    assert ids == expected
    assert report["verdict"]["passed"], report["verdict"]


def test_two_robots_two_python_nodes_in_lock_step(two_robots_export: Path, tmp_path: Path) -> None:
    log = tmp_path / "frames.log"
    report = hil(None, two_robots_export, tmp_path, "--node", "python", "--episodes", "3", "--log", str(log))
    _check_two_robots(report, 3, log)


@pytest.mark.slow
def test_two_robots_two_c_nodes_on_one_vcan_equal_the_simulation_on_20_episodes(
    guest: Guest, two_robots_export: Path, tmp_path: Path
) -> None:
    log = tmp_path / "frames.log"
    report = hil(guest, two_robots_export, tmp_path, "--episodes", "20", "--log", str(log))
    _check_two_robots(report, 20, log)


def _check_kill(report: dict[str, Any]) -> None:
    rows = {(r["seed"], r["node"]): r for r in report["per_episode"]}
    # Episode 0 ran normally; node 1 was killed before step 3 of episode 1; the run ends with that episode.
    assert set(rows) == {(0, 0), (0, 1), (1, 0), (1, 1)}
    killed, other = rows[(1, 1)], rows[(1, 0)]
    assert killed["outcome"] == "fault" and killed["injected"] == ["kill"] and "exited" in killed["fault"]
    assert other["outcome"] == "success" and other["fault"] is None  # its node kept driving it
    assert rows[(0, 0)]["outcome"] == rows[(0, 1)]["outcome"] == "success"
    assert report["verdict"]["passed"], report["verdict"]  # the kill's episode is exempt (--allow-faults)


def test_killing_one_python_node_stops_only_its_robot(two_robots_export: Path, tmp_path: Path) -> None:
    args = ["--node", "python", "--episodes", "3", "--kill-node", "1@1:3", "--allow-faults"]
    _check_kill(hil(None, two_robots_export, tmp_path, *args, "--timeout-ms", "500"))


@pytest.mark.slow
def test_killing_one_c_node_stops_only_its_robot(
    guest: Guest, two_robots_export: Path, tmp_path: Path
) -> None:
    _check_kill(
        hil(guest, two_robots_export, tmp_path, "--episodes", "3", "--kill-node", "1@1:3", "--allow-faults")
    )


@pytest.mark.parametrize(
    ("extra", "said"),
    [
        (["--nodes", "3"], "one node per robot"),
        (["--inject", "loss"], "drop --inject"),
        (["--kill-node", "2@0:1"], "nodes 0..1"),
    ],
)
def test_two_robot_runs_refuse_what_does_not_apply(
    two_robots_export: Path, tmp_path: Path, extra: list[str], said: str, capsys: pytest.CaptureFixture[str]
) -> None:
    args = ["hil", "run", "--export-dir", str(two_robots_export), "--json", str(tmp_path / "r.json")]
    assert main([*args, "--node", "python", *extra]) == 2
    err = capsys.readouterr().err
    assert said in err and len(err.strip().splitlines()) == 1, err
    assert not (tmp_path / "r.json").exists()


def test_hil_bench_refuses_the_two_robot_scenario_in_one_line(
    two_robots_export: Path, tmp_path: Path, capsys: pytest.CaptureFixture[str]
) -> None:
    out = tmp_path / "b.json"
    assert main(["hil", "bench", "--export-dir", str(two_robots_export), "--json", str(out)]) == 2
    err = capsys.readouterr().err
    assert "one node on one robot" in err and len(err.strip().splitlines()) == 1, err
    assert not out.exists()
