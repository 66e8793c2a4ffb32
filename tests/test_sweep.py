"""Sweeps beyond one process: a tiny bench on a local Ray instance (one task per run, a failed run reported
without losing the others, the table rebuilt from the run folders) and the bootstrap intervals."""

from __future__ import annotations

import json
from pathlib import Path

import pytest

from embedrl.cli import main
from embedrl.train.errors import TrainError
from embedrl.train.study_benchmark import MIN_SEEDS_FOR_INTERVAL, median_ci
from embedrl.train.sweep import run_all


@pytest.mark.training
def test_a_tiny_bench_on_local_ray_reports_a_failed_run_and_keeps_the_others(
    tmp_path: Path, capsys: pytest.CaptureFixture[str]
) -> None:
    out = tmp_path / "bench"
    broken = out / "runs" / "td3-seed1"
    broken.mkdir(parents=True)
    (broken / "config.json").write_text("{damaged")  # this run cannot resume: its task fails
    argv = ["bench", "--algos", "td3", "--seeds", "2", "--max-steps", "300", "--eval-episodes", "2",
            "--workers", "2", "--ray", "local", "--out", str(out)]  # fmt: skip
    assert main(argv) == 1
    captured = capsys.readouterr()
    assert "1 run(s) failed" in captured.err
    assert captured.err.startswith("warning: td3: a budget of 300 steps ends within the random warm-up")
    table = (out / "bench.md").read_text()
    assert "Failed: td3 seed 1: UsageError: cannot resume" in table
    data = json.loads((out / "bench.json").read_text())
    assert [r["seed"] for r in data["runs"]] == [0] and data["failed"]
    assert json.loads((out / "runs" / "td3-seed0" / "result.json").read_text())["evaluation"]["episodes"] == 2
    # the table again from the folders, on another machine or later: the same rows
    assert main(["bench", "--from", str(out), "--out", str(tmp_path / "again")]) == 0
    assert json.loads((tmp_path / "again" / "bench.json").read_text())["rows"] == data["rows"]
    for folder in (out, tmp_path / "again"):  # the learning curves from the run folders, both ways
        assert (folder / "learning_curves.png").read_bytes()[:8] == b"\x89PNG\r\n\x1a\n"


def _double(x: int) -> dict[str, int]:
    if x == 3:
        raise ValueError("three is not allowed")
    return {"x": 2 * x}


@pytest.mark.parametrize("workers", [1, 2])
def test_the_pool_keeps_order_and_reports_each_failure(workers: int) -> None:
    results, failures = run_all(_double, [1, 2, 3, 4], workers)
    assert results == [{"x": 2}, {"x": 4}, None, {"x": 8}]
    assert [(f.job, f.error) for f in failures] == [(3, "ValueError: three is not allowed")]


@pytest.mark.training
def test_a_sweep_where_every_run_failed_says_so_in_one_line(
    tmp_path: Path, capsys: pytest.CaptureFixture[str]
) -> None:
    with pytest.raises(TrainError, match=r"every run failed \(1\); the first: 3: ValueError: three"):
        run_all(_double, [3], 1)
    broken = tmp_path / "b" / "runs" / "td3-seed0"
    broken.mkdir(parents=True)
    (broken / "config.json").write_text("{damaged")  # the only run cannot resume: it fails
    assert (
        main(["bench", "--algos", "td3", "--seeds", "1", "--max-steps", "100", "--out", str(tmp_path / "b")])
        == 2
    )
    err = capsys.readouterr().err.strip().splitlines()
    assert err[-1].startswith("error: every run failed (1); the first: td3 seed 0:"), err


def test_intervals_need_three_seeds_and_contain_the_median() -> None:
    assert median_ci([0.5, 0.9]) == (0.7, None, None)
    assert median_ci([0.97, 0.97, 0.97]) == (0.97, None, None)  # nothing to bound
    values = [0.90, 0.95, 0.97, 0.99, 1.0]
    median, low, high = median_ci(values)
    assert MIN_SEEDS_FOR_INTERVAL == 3 and median == 0.97
    assert low is not None and high is not None and min(values) <= low <= median <= high <= max(values)
    assert median_ci(values) == (median, low, high)  # seeded: the same interval every time


def test_a_table_from_folders_without_runs_is_refused(
    tmp_path: Path, capsys: pytest.CaptureFixture[str]
) -> None:
    assert main(["bench", "--from", str(tmp_path), "--out", str(tmp_path / "t")]) == 2
    assert "no finished runs" in capsys.readouterr().err
