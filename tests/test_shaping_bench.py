"""``embedrl shaping``: the from-scratch comparison of the study's reward and potential-based shaping."""

from __future__ import annotations

import csv
import json
from pathlib import Path

import pytest

from embedrl.cli import main
from embedrl.train.errors import UsageError
from embedrl.train.shaping_bench import run_shaping


def _returns(run: Path) -> list[float]:
    with (run / "curve.csv").open() as f:
        return [float(r["return"]) for r in csv.DictReader(f)]


def test_shaping_comparison_writes_table_runs_and_curves(tmp_path: Path) -> None:
    out = tmp_path / "shaping"
    table = run_shaping(["td3", "ppo"], 1, 7, "tuned", out, 700, 5, 1, 2.0, ("net_arch=16,16",))
    lines = table.splitlines()
    assert lines[0] == "| | TD3 eq. 19 | TD3 shaped | PPO eq. 19 | PPO shaped |"
    assert lines[2].startswith("| runs reaching the study's criterion | 0 / 1 | 0 / 1 |")
    assert (out / "shaping.md").read_text() == table
    assert (out / "shaping.png").stat().st_size > 10_000
    report = json.loads((out / "shaping.json").read_text())
    assert report["shaping_gain"] == 2.0 and report["seeds"] == [7]
    runs = {(r["algo"], r["reward_variant"]): r for r in report["runs"]}
    assert set(runs) == {("td3", "thesis"), ("td3", "shaped"), ("ppo", "thesis"), ("ppo", "shaped")}
    for (algo, reward), run in runs.items():
        config = json.loads((Path(run["run"]) / "config.json").read_text())
        hyper = config["hyperparameters"]
        assert hyper["reward"] == reward and (reward == "thesis" or hyper["shaping_gain"] == 2.0)
        assert hyper["demonstrations" if algo == "td3" else "warm_start_demonstrations"] == 0  # from scratch
        assert not (Path(run["run"]) / "warm_start_model.zip").exists()
    # TD3's first 10,000 steps are random actions, the same for both rewards: the criterion's returns are
    # then the same, because both count the eq. 19 return only (the shaping term left out).
    thesis, shaped = (_returns(Path(runs[("td3", r)]["run"])) for r in ("thesis", "shaped"))
    assert len(thesis) > 20 and thesis == shaped
    # Finished runs are reused: a second call trains nothing and gives the same table.
    stamp = (Path(runs[("ppo", "shaped")]["run"]) / "summary.json").stat().st_mtime_ns
    assert run_shaping(["td3", "ppo"], 1, 7, "tuned", out, 700, 5, 1, 2.0, ("net_arch=16,16",)) == table
    assert (Path(runs[("ppo", "shaped")]["run"]) / "summary.json").stat().st_mtime_ns == stamp


def _column(table: str, label: str) -> list[str]:
    """The cells of the table's row that starts with ``label``."""
    row = next(line for line in table.splitlines() if line.startswith(f"| {label}"))
    return [cell.strip() for cell in row.strip("|").split("|")[1:]]


def test_walker_shaping_compares_the_decks_four_stages_measured_alike(tmp_path: Path) -> None:
    out = tmp_path / "walker"
    overrides = ("net_arch=16,16", "learning_starts=300")
    table = run_shaping(["td3"], 1, 5, "tuned", out, 600, 3, 1, 1.0, overrides, scenario="walker")
    lines = table.splitlines()
    assert lines[0] == (
        "| median [worst, best] over seeds | TD3 `velocity` | TD3 `upright` | TD3 `effort` | TD3 `deck` |"
    )
    block = 32  # the walker's TD3 collects and updates in blocks: the budget rounded up to one
    assert _column(table, "env steps trained") == [str(-(-600 // block) * block)] * 4
    assert (out / "shaping.md").read_text() == table
    assert (out / "shaping.png").stat().st_size > 10_000
    report = json.loads((out / "shaping.json").read_text())
    assert report["scenario"] == "walker" and report["shaping_gain"] is None
    assert report["rewards"] == ["velocity", "upright", "effort", "deck"]
    runs = {r["reward_variant"]: r for r in report["runs"]}
    assert set(runs) == set(report["rewards"])
    for reward, run in runs.items():
        assert (
            json.loads((Path(run["run"]) / "config.json").read_text())["hyperparameters"]["reward"] == reward
        )
        evaluation = run["evaluation"]
        assert evaluation["episodes"] == 3  # every stage tested on the same env and seeds
        falls = 100 * evaluation["collisions"] / 3
        assert (
            _column(table, "test episodes without a fall")[list(runs).index(reward)] == f"{100 - falls:.0f}"
        )
        assert (
            _column(table, "test distance")[list(runs).index(reward)]
            == f"{evaluation['mean_distance_m']:.2f}"
        )
    # The first 300 steps are the same random actions for every stage: the same episodes, the same
    # distances, but each stage's own return (the velocity stage has neither bonus nor penalties).
    early = [_early_distances(Path(runs[r]["run"]), 300) for r in report["rewards"]]
    assert len(early[0]) >= 3 and all(e == early[0] for e in early)
    returns = {r: _returns(Path(runs[r]["run"]))[: len(early[0])] for r in report["rewards"]}
    assert returns["velocity"] != returns["upright"] and returns["effort"] == returns["deck"]
    # The table of the finished runs alone: nothing trained, the same cells; a run not trained yet is named.
    stamp = (Path(runs["deck"]["run"]) / "summary.json").stat().st_mtime_ns
    again = run_shaping(
        ["td3"], 2, 5, "tuned", out, 600, 3, 1, 1.0, overrides, scenario="walker", finished_only=True
    )
    assert again.splitlines()[:12] == lines[:12]
    assert "Not finished at this budget (4 of 8 runs): td3-velocity-seed6, td3-upright-seed6" in again
    assert (Path(runs["deck"]["run"]) / "summary.json").stat().st_mtime_ns == stamp
    with pytest.raises(UsageError, match="has finished 900 env steps"):
        run_shaping(
            ["td3"], 1, 5, "tuned", out, 900, 3, 1, 1.0, overrides, scenario="walker", finished_only=True
        )


def _early_distances(run: Path, steps: int) -> list[float]:
    with (run / "episode_sums.csv").open() as f:
        return [float(r["distance"]) for r in csv.DictReader(f) if int(r["steps"]) <= steps]


@pytest.mark.parametrize(
    ("argv", "said"),
    [
        (["--gain", "-1"], "--gain must be a finite number >= 0"),
        (["--gain", "nan"], "--gain must be a finite number >= 0"),
        (["--set", "nosuch=1"], "expected NAME=VALUE"),
        (["--scenario", "walker", "--algos", "ppo"], "no walker preset for ppo"),
    ],
)
def test_bad_shaping_arguments_are_one_line_errors(
    argv: list[str], said: str, tmp_path: Path, capsys: pytest.CaptureFixture[str]
) -> None:
    assert main(["shaping", "--out", str(tmp_path / "s"), *argv]) == 2
    assert said in capsys.readouterr().err
    assert not (tmp_path / "s").exists()


def test_every_algorithm_can_learn_from_scratch() -> None:
    from embedrl.train.config import ALGOS
    from embedrl.train.shaping_bench import FROM_SCRATCH

    assert set(FROM_SCRATCH) == set(ALGOS)
