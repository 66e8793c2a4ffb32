"""``embedrl tune``: a tiny Optuna search, resumed, its best preset read by ``embedrl train --preset``."""

from __future__ import annotations

import json
from pathlib import Path
from typing import Any

import optuna
import pytest
from optuna.trial import TrialState

from embedrl.cli import main
from embedrl.train.errors import UsageError
from embedrl.train.scenarios import DEFAULT_SCENARIO
from embedrl.train.tune import RUNGS, SPACE, Search, _only_search, run_tune, sample


@pytest.mark.training
def test_a_tiny_search_resumes_and_its_best_preset_trains(
    tmp_path: Path, capsys: pytest.CaptureFixture[str]
) -> None:
    out = tmp_path / "study"
    argv = ["tune", "--algo", "td3", "--trials", "2", "--max-steps", "300", "--out", str(out)]
    assert main(argv) == 0
    best = json.loads((out / "best_preset.json").read_text())
    assert best["base_preset"] == "tuned" and 0.0 <= best["validation_success"] <= 1.0
    # 300 steps end within the tuned preset's random warm-up: said before the search, on the best's line
    # and in the preset file
    printed = capsys.readouterr()
    assert best["untrained"] is True and "% (UNTRAINED: no trial had a training update), " in printed.out
    warnings = [line for line in printed.err.splitlines() if line.startswith("warning:")]
    assert len(warnings) == 1 and "ends within the random warm-up (10,000 steps" in warnings[0]
    assert {o.split("=")[0] for o in best["overrides"]} == set(SPACE)  # TD3 has every searched field
    assert len((out / "trials.md").read_text().splitlines()) == 2 + 2
    assert sorted(p.name for p in (out / "trials").iterdir()) == ["trial-0", "trial-1"]
    # resumed: the study in study.db counts its trials; one more is run, the first two are not redone
    assert main([*argv[:4], "3", *argv[5:]]) == 0
    assert len((out / "trials.md").read_text().splitlines()) == 2 + 3
    capsys.readouterr()
    run = tmp_path / "run"
    argv = ["train", "--preset", str(out / "best_preset.json"), "--max-steps", "300", "--out", str(run)]
    assert main(argv) == 0
    config = json.loads((run / "config.json").read_text())
    assert (
        config["preset"] == "tuned"
        and config["overrides"] == json.loads((out / "best_preset.json").read_text())["overrides"]
    )


@pytest.mark.parametrize(
    "content", ["{not json", '{"base_preset": "fast", "overrides": []}', '{"overrides": 3}']
)
def test_a_bad_preset_file_is_refused_in_one_line(
    tmp_path: Path, capsys: pytest.CaptureFixture[str], content: str
) -> None:
    bad = tmp_path / "preset.json"
    bad.write_text(content)
    assert main(["train", "--preset", str(bad), "--out", str(tmp_path / "run")]) == 2
    err = capsys.readouterr().err.strip()
    assert "not a preset file of `embedrl tune`" in err and len(err.splitlines()) == 1
    assert not (tmp_path / "run").exists()


@pytest.mark.training
def test_a_tiny_search_on_ray_tune_shares_its_study_with_the_local_search(
    tmp_path: Path, capsys: pytest.CaptureFixture[str], monkeypatch: pytest.MonkeyPatch
) -> None:
    """Ray Tune runs the trials (Optuna's sampler through ``OptunaSearch``) into the same study.db: a search
    resumed without Ray counts them. Relative paths: Ray runs each trial in a folder of its own."""
    monkeypatch.chdir(tmp_path)
    argv = ["tune", "--algo", "td3", "--trials", "2", "--max-steps", "300", "--out", "my study"]
    assert main([*argv, "--ray", "local", "--workers", "2"]) == 0
    out = tmp_path / "my study"
    assert len(list((out / "trials").glob("ray-*"))) == 2 and (out / "ray").is_dir()
    rows = (out / "trials.md").read_text().splitlines()[2:]
    assert len(rows) == 2 and all("| complete |" in row and "| 3/3 |" in row for row in rows)
    best = json.loads((out / "best_preset.json").read_text())
    assert {o.split("=")[0] for o in best["overrides"]} == set(SPACE)
    assert main([*argv[:4], "3", *argv[5:]]) == 0  # one more, here: the two Ray trials are not redone
    assert len((out / "trials.md").read_text().splitlines()) == 2 + 3
    assert (out / "trials" / "trial-2").is_dir() and not (out / "trials" / "trial-0").exists()
    assert "wrote my study/best_preset.json" in capsys.readouterr().out


def test_no_cluster_to_join_is_one_line_and_leaves_no_folder(
    tmp_path: Path, capsys: pytest.CaptureFixture[str], monkeypatch: pytest.MonkeyPatch
) -> None:
    monkeypatch.delenv("RAY_ADDRESS", raising=False)
    out = tmp_path / "study"
    argv = [
        "tune",
        "--algo",
        "td3",
        "--trials",
        "1",
        "--max-steps",
        "300",
        "--out",
        str(out),
        "--ray",
        "auto",
    ]
    assert main(argv) == 2
    lines = capsys.readouterr().err.strip().splitlines()
    errors = [line for line in lines if not line.startswith("warning: ")]  # the tiny budget's own warning
    assert len(errors) == 1 and "Ray instance" in errors[0] and not out.exists()


def _quick_objective(trial: Any, search: Search, fields: set[str]) -> float:
    """A trial that samples its changes and reports every evaluation without training."""
    sample(trial, fields)
    for rung in range(1, RUNGS + 1):
        trial.report(0.5, rung)
    return 0.5


def test_a_search_resumed_after_kill_and_interrupt_fails_the_stale_trial_and_samples_afresh(
    tmp_path: Path, monkeypatch: pytest.MonkeyPatch
) -> None:
    # The study as a search left it: trial 0 complete, trial 1 interrupted (Ctrl-C: failed), trial 2
    # running when the search was killed (kill -9: running for ever).
    search = Search("td3", DEFAULT_SCENARIO, 300, tmp_path)
    fields = set(SPACE)
    study = optuna.create_study(study_name=search.name, storage=search.storage, direction="maximize",
                                sampler=optuna.samplers.TPESampler(seed=search.seed))  # fmt: skip
    for state in ("complete", "fail", "running"):
        trial = study.ask()
        _quick_objective(trial, search, fields)
        if state != "running":
            study.tell(trial, 0.5 if state == "complete" else None, state=getattr(TrialState, state.upper()))
    monkeypatch.setattr("embedrl.train.tune._objective", _quick_objective)
    run_tune(search, 3)
    trials = optuna.load_study(study_name=search.name, storage=search.storage).trials
    assert [t.state for t in trials] == [TrialState.COMPLETE, TrialState.FAIL, TrialState.FAIL,
                                         TrialState.COMPLETE, TrialState.COMPLETE]  # fmt: skip
    earlier = [t.params for t in trials[:3]]
    assert all(t.params not in earlier for t in trials[3:])  # not the first trials' values again


def test_a_second_search_in_the_same_folder_is_refused(
    tmp_path: Path, monkeypatch: pytest.MonkeyPatch
) -> None:
    search = Search("td3", DEFAULT_SCENARIO, 300, tmp_path)
    monkeypatch.setattr("embedrl.train.tune._objective", _quick_objective)
    with _only_search(search), pytest.raises(UsageError, match="another `embedrl tune` is searching"):
        run_tune(search, 1)
    run_tune(search, 1)  # the folder free again
