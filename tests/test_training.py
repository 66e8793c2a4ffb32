"""Training: short runs of each algorithm, reproducibility, the stop criterion, resume, the benchmark."""

from __future__ import annotations

import csv
import json
import signal
import subprocess
import sys
import time
from pathlib import Path
from typing import Any

import numpy as np
import pytest
from stable_baselines3 import PPO, TD3

from embedrl.cli import main
from embedrl.train.config import ALGOS, Budget, preset, untrained_budget
from embedrl.train.models import load_model_policy
from embedrl.train.monitor import CURVE_FIELDS, STOP_THRESHOLD, STOP_WINDOW, RunMonitor
from embedrl.train.trainer import train

SHORT = Budget(max_steps=600, checkpoint_every=300, eval_every=10_000)


def _curve(run: Path) -> list[dict[str, str]]:
    with (run / "curve.csv").open() as f:
        return list(csv.DictReader(f))


class _FakeMonitor(RunMonitor):
    """RunMonitor fed by hand: no model, no environment."""

    def __init__(
        self,
        run: Path,
        budget: Budget | None = None,
        validations: list[tuple[float, float]] | None = None,
        trained: list[bool] | None = None,
    ) -> None:
        (run / "curve.csv").write_text(",".join(CURVE_FIELDS) + "\n")
        scripted = iter(validations or [])
        learnt = iter(trained) if trained is not None else None
        self.saved_best: list[int] = []
        super().__init__(
            run, budget or Budget(), {}, lambda: None, lambda: next(scripted), progress=False,
            save_best=lambda: self.saved_best.append(self.state["best"]["step"]),
            trained=lambda: True if learnt is None else next(learnt),
        )  # fmt: skip
        self.pending_q0 = 0.0


@pytest.mark.parametrize("stop", ["validation", "budget"])
def test_validation_keeps_the_best_checkpoint_and_stops_at_the_target(tmp_path: Path, stop: str) -> None:
    # Success rates over training: rising, a collapse, the target, then more.
    script = [(0.40, -1.0), (0.90, 1.0), (0.90, 1.5), (0.20, -3.0), (0.97, 2.5), (0.99, 2.6)]
    monitor = _FakeMonitor(tmp_path, Budget(target_success=0.97, stop=stop), script)
    stopped_at = None
    for k in range(len(script)):
        monitor.evaluation(1000 * (k + 1))
        if monitor.stop_now():
            stopped_at = 1000 * (k + 1)
            break
    # A better one replaces the best; an equal success with a higher return too; a collapse never does.
    if stop == "validation":
        assert stopped_at == 5000 and monitor.saved_best == [1000, 2000, 3000, 5000]
    else:
        assert stopped_at is None and monitor.saved_best == [1000, 2000, 3000, 5000, 6000]
    assert monitor.state["target_step"] == 5000
    assert monitor.state["first_deterministic_criterion_step"] == 5000  # mean return >= 2
    with (tmp_path / "evaluations.csv").open() as f:
        rows = list(csv.DictReader(f))
    assert [int(r["steps"]) for r in rows] == [1000 * (k + 1) for k in range(len(rows))]
    assert float(rows[3]["success_rate"]) == pytest.approx(0.2)


def test_the_study_stop_rule_waits_for_the_study_criterion(tmp_path: Path) -> None:
    monitor = _FakeMonitor(tmp_path, Budget(stop="study"), [(1.0, 3.0)])
    monitor.evaluation(1000)
    assert monitor.state["target_step"] == 1000 and not monitor.stop_now()
    for i in range(STOP_WINDOW):
        monitor._episode(3.0, 10, 2000 + i)
    assert monitor.stop_now()


def test_stop_criterion_fires_exactly_when_the_window_mean_reaches_two(tmp_path: Path) -> None:
    monitor = _FakeMonitor(tmp_path)
    returns = [-2.0] * 60 + [3.0] * 100
    for i, r in enumerate(returns):
        monitor._episode(r, 10, 10 * (i + 1))
        window = returns[max(0, i + 1 - STOP_WINDOW) : i + 1]
        crossed = len(window) == STOP_WINDOW and np.mean(window) >= STOP_THRESHOLD
        if crossed:
            break
        assert monitor.state.get("criterion_step") is None
    # 60 x -2 then 3s: the window of 50 first averages >= 2 when 40 of its episodes are 3s (i = 99).
    assert monitor.state["criterion_episode"] == 100 and monitor.state["criterion_step"] == 1000
    rows = _curve(tmp_path)
    assert len(rows) == 100 and float(rows[-1]["average50"]) == pytest.approx(2.0)


@pytest.mark.slow
@pytest.mark.parametrize("algo", ALGOS)
def test_short_run_produces_a_model_that_loads_and_evaluates(algo: str, tmp_path: Path) -> None:
    run = tmp_path / algo
    summary = train(algo, "thesis", 0, run, SHORT)
    assert summary["total_steps"] >= 600 and summary["total_episodes"] == len(_curve(run))
    for name in ("model.zip", "config.json", "curve.csv", "summary.json", "progress.png", "checkpoint"):
        assert (run / name).exists(), name
    assert (run / "vecnormalize.pkl").is_file() == (run / "vecnormalize.npz").is_file() == ("ppo" in algo)
    config = json.loads((run / "config.json").read_text())
    assert (
        config["algo"] == algo and config["seed"] == 0 and config["hyperparameters"]["net_arch"] == [100, 100]
    )
    assert config["provenance"]["versions"]["stable-baselines3"] == "2.9.2"
    out = tmp_path / "eval.json"
    assert main(["eval", str(run / "model.zip"), "--episodes", "3", "--seed", "5", "--json", str(out)]) == 0
    assert json.loads(out.read_text())["episodes"] == 3


@pytest.mark.slow
def test_same_seed_gives_identical_actions(tmp_path: Path) -> None:
    budget = Budget(max_steps=1500, checkpoint_every=10_000, eval_every=10_000)
    train("td3", "thesis", 3, tmp_path / "a", budget)
    train("td3", "thesis", 3, tmp_path / "b", budget)
    obs = np.random.default_rng(0).uniform(-1, 1, size=(50, 6)).astype(np.float32)
    a, b = (load_model_policy(tmp_path / r / "model.zip") for r in ("a", "b"))
    assert np.stack([a(o) for o in obs]).tobytes() == np.stack([b(o) for o in obs]).tobytes()
    assert _curve(tmp_path / "a") == _curve(tmp_path / "b")


@pytest.mark.slow
def test_a_run_killed_and_resumed_ends_bit_identical_to_the_same_run_uninterrupted(tmp_path: Path) -> None:
    budget = ["--max-steps", "2500", "--checkpoint-every", "500", "--eval-every", "100000"]
    new = ["train", "--algo", "td3", "--preset", "thesis", "--seed", "4", *budget]
    assert main([*new, "--out", str(tmp_path / "whole")]) == 0
    run = tmp_path / "killed"
    proc = subprocess.Popen(
        [sys.executable, "-m", "embedrl.cli", *new, "--out", str(run)],
        stdout=subprocess.DEVNULL,
        stderr=subprocess.DEVNULL,
    )
    deadline = time.monotonic() + 300
    while not (run / "checkpoint" / "state.json").is_file() and time.monotonic() < deadline:
        time.sleep(0.05)
    time.sleep(0.5)  # somewhere after the first checkpoint, wherever SIGKILL lands
    proc.send_signal(signal.SIGKILL)
    proc.wait()
    assert not (run / "summary.json").exists()
    state: dict[str, Any] = json.loads((run / "checkpoint" / "state.json").read_text())
    assert main(["train", "--resume", str(run)]) == 0  # everything from the run's own config
    assert json.loads((run / "summary.json").read_text())["total_steps"] == 2500 > state["steps"]
    whole, resumed = TD3.load(tmp_path / "whole" / "model.zip"), TD3.load(run / "model.zip")
    obs = np.random.default_rng(0).uniform(-1, 1, (256, 6)).astype(np.float32)
    assert np.array_equal(
        whole.predict(obs, deterministic=True)[0], resumed.predict(obs, deterministic=True)[0]
    )
    assert (run / "curve.csv").read_text() == (tmp_path / "whole" / "curve.csv").read_text()


def test_an_untrained_policy_is_the_best_only_until_a_trained_one_is_evaluated(tmp_path: Path) -> None:
    """Within the random warm-up the actor is the fresh one: it crashes at once (-2), which scores better
    than the wandering of the first trained actors (-25); it must not be shipped as the best."""
    script = [(0.0, -2.0), (0.0, -25.0), (0.0, -20.0), (0.0, -22.0)]
    monitor = _FakeMonitor(tmp_path, Budget(), script, trained=[False, True, True, True])
    monitor.evaluation(1000)
    assert monitor.state["best"] == {"step": 1000, "success": 0.0, "mean_return": -2.0, "trained": False}
    for k in (2, 3, 4):
        monitor.evaluation(1000 * k)
    assert monitor.state["best"]["step"] == 3000 and monitor.state["best"]["trained"] is True
    assert monitor.saved_best == [1000, 2000, 3000]


def test_only_an_off_policy_budget_within_its_warm_up_trains_nothing() -> None:
    assert untrained_budget(preset("td3", "tuned"), 10_000) is not None  # SB3 trains once steps > 10,000
    assert untrained_budget(preset("td3", "tuned"), 10_001) is None
    assert untrained_budget(preset("td3", "thesis"), 1) is None  # the study's agents learn from step one
    assert untrained_budget(preset("ppo", "tuned"), 1) is None  # PPO updates after its first rollout


@pytest.mark.training
@pytest.mark.parametrize("learning_starts", [10_000, 100])
def test_a_budget_within_the_warm_up_warns_and_the_run_says_it_is_untrained(
    tmp_path: Path, capsys: pytest.CaptureFixture[str], learning_starts: int
) -> None:
    """SB3 updates an off-policy agent only after ``learning_starts`` steps: a smaller budget trains nothing.
    It is allowed (tiny test runs), but said in one line before training, in summary.json and at the end."""
    run = tmp_path / "run"
    argv = ["train", "--algo", "td3", "--max-steps", "300", "--eval-every", "300", "--out", str(run),
            "--set", "demonstrations=2", "--set", f"learning_starts={learning_starts}"]  # fmt: skip
    assert main(argv) == 0
    out, err = capsys.readouterr()
    summary = json.loads((run / "summary.json").read_text())
    warnings = [line for line in err.splitlines() if line.startswith("warning:")]
    if learning_starts < 300:
        assert summary["untrained"] is False and summary["updates"] > 0 and not warnings
        assert summary["best_validation"]["trained"] is True
        return
    assert summary["untrained"] is True and summary["updates"] == 0
    assert summary["selected"] == "best validation" and summary["best_validation"]["trained"] is False
    assert warnings == [
        "warning: a budget of 300 steps ends within the random warm-up (10,000 steps, learning_starts): no "
        "training update, the policy stays untrained; give a larger --max-steps or --set learning_starts=N",
        f"warning: {run / 'model.zip'} is an untrained policy: it never had a training update",
    ]
    assert f"{'untrained':<36}  True" in out.splitlines()


def _short_run(run: Path) -> None:
    """A TD3 run with two checkpoints (seconds)."""
    assert main(["train", "--algo", "td3", "--preset", "thesis", "--out", str(run), "--max-steps", "400",
                 "--checkpoint-every", "200", "--eval-every", "100000"]) == 0  # fmt: skip


@pytest.mark.training
def test_resume_refuses_flags_that_contradict_the_run(
    tmp_path: Path, capsys: pytest.CaptureFixture[str]
) -> None:
    run = tmp_path / "run"
    _short_run(run)
    capsys.readouterr()
    for flags, said in (
        (["--max-steps", "300"], "--max-steps 300 (the run has 400)"),
        (["--algo", "sac"], "--algo sac (the run has td3)"),
        (["--seed", "5"], "--seed 5 (the run has 0)"),
        (["--keep-training"], "--stop budget (the run has validation)"),
        (["--scenario", "moving-shelf"], "--scenario moving-shelf (the run has static)"),
        (["--set", "gamma=0.5"], "a resumed run keeps its own"),
        (["--out", str(tmp_path / "x")], "not both"),
    ):
        assert main(["train", "--resume", str(run), *flags]) == 2, flags
        err = capsys.readouterr().err
        assert said in err and len(err.strip().splitlines()) == 1, err
    # flags equal to the run's own are fine (nothing left to train: the budget is spent)
    assert main(["train", "--resume", str(run), "--max-steps", "400", "--algo", "td3"]) == 0


@pytest.mark.training
def test_a_resumed_run_trains_on_past_its_budget_and_records_it(tmp_path: Path) -> None:
    run = tmp_path / "run"
    _short_run(run)
    episodes = len((run / "curve.csv").read_text().splitlines())
    assert main(["train", "--resume", str(run), "--max-steps", "700"]) == 0
    summary = json.loads((run / "summary.json").read_text())
    assert summary["total_steps"] == 700
    assert len((run / "curve.csv").read_text().splitlines()) > episodes  # the same curve, continued
    config = json.loads((run / "config.json").read_text())
    assert config["budget"]["max_steps"] == 700
    assert config["extensions"] == [
        {"from_max_steps": 400, "to_max_steps": 700, "from_stop": config["budget"]["stop"],
         "to_stop": config["budget"]["stop"]}
    ]  # fmt: skip
    assert main(["train", "--resume", str(run)]) == 0  # the new budget is the run's own now
    assert json.loads((run / "summary.json").read_text())["total_steps"] == 700


@pytest.mark.training
def test_resuming_a_run_that_stopped_at_its_stop_rule_needs_keep_training(
    tmp_path: Path, capsys: pytest.CaptureFixture[str]
) -> None:
    run = tmp_path / "run"
    _short_run(run)
    state_file = run / "checkpoint" / "state.json"
    state = json.loads(state_file.read_text())
    rule = json.loads((run / "config.json").read_text())["budget"]["stop"]
    state["target_step" if rule == "validation" else "criterion_step"] = state["steps"]  # as if it fired
    state_file.write_text(json.dumps(state))
    config = (run / "config.json").read_text()
    capsys.readouterr()
    assert main(["train", "--resume", str(run), "--max-steps", "700"]) == 2
    err = capsys.readouterr().err
    assert f"stopped at its stop rule (--stop {rule}) at step 400; add --keep-training" in err
    assert len(err.strip().splitlines()) == 1 and (run / "config.json").read_text() == config  # unchanged
    assert main(["train", "--resume", str(run), "--max-steps", "700", "--keep-training"]) == 0
    assert json.loads((run / "summary.json").read_text())["total_steps"] == 700
    extension = json.loads((run / "config.json").read_text())["extensions"][-1]
    assert extension == {"from_max_steps": 400, "to_max_steps": 700, "from_stop": rule, "to_stop": "budget"}


@pytest.mark.training
def test_checkpoints_are_swapped_atomically_and_a_bad_one_is_a_clear_error(
    tmp_path: Path, capsys: pytest.CaptureFixture[str]
) -> None:
    run = tmp_path / "run"
    _short_run(run)
    assert sorted(p.name for p in run.iterdir() if p.name.startswith("checkpoint")) == ["checkpoint"]
    # a kill between the swap's two renames leaves the previous complete checkpoint as checkpoint.old
    (run / "checkpoint").rename(run / "checkpoint.old")
    (run / "checkpoint.partial").mkdir()  # and an unfinished new one, never used
    assert main(["train", "--resume", str(run)]) == 0
    assert (run / "checkpoint" / "state.json").is_file() and not (run / "checkpoint.old").exists()
    capsys.readouterr()
    replay = run / "checkpoint" / "replay_buffer.pkl"
    replay.write_bytes(replay.read_bytes()[:1000])  # truncated
    assert main(["train", "--resume", str(run)]) == 2
    err = capsys.readouterr().err
    assert "is damaged" in err and "Traceback" not in err and len(err.strip().splitlines()) == 1
    curve = (run / "curve.csv").read_text()
    for name in ("state.json",):
        (run / "checkpoint" / name).unlink()
    assert main(["train", "--resume", str(run)]) == 2
    assert "no complete checkpoint" in capsys.readouterr().err
    assert (run / "curve.csv").read_text() == curve  # nothing overwritten, no fresh start


def test_new_run_refuses_a_used_directory_and_resume_needs_a_run(
    tmp_path: Path, capsys: pytest.CaptureFixture[str]
) -> None:
    (tmp_path / "used").mkdir()
    (tmp_path / "used" / "x").write_text("x")
    assert main(["train", "--algo", "td3", "--out", str(tmp_path / "used")]) == 2
    assert "use --resume" in capsys.readouterr().err
    assert main(["train", "--resume", str(tmp_path)]) == 2
    assert "not a run directory" in capsys.readouterr().err


def test_eval_rejects_a_model_that_is_not_an_sb3_zip(
    tmp_path: Path, capsys: pytest.CaptureFixture[str]
) -> None:
    (tmp_path / "model.pt").write_bytes(b"x")
    assert main(["eval", str(tmp_path / "model.pt"), "--episodes", "2"]) == 2
    assert "give a Stable-Baselines3 model" in capsys.readouterr().err
    (tmp_path / "broken.zip").write_bytes(b"PK broken")
    assert main(["eval", str(tmp_path / "broken.zip"), "--episodes", "2"]) == 2
    assert "not a readable Stable-Baselines3 model" in capsys.readouterr().err


@pytest.mark.slow
def test_bench_on_a_tiny_budget_writes_both_formats_with_all_rows(tmp_path: Path) -> None:
    assert (
        main(
            [
                "bench",
                "--algos",
                "td3",
                "ppo",
                "--seeds",
                "2",
                "--preset",
                "thesis",
                "--out",
                str(tmp_path),
                "--max-steps",
                "600",
                "--eval-episodes",
                "3",
                "--workers",
                "2",
                "--seed-offset",
                "100",
            ]
        )
        == 0
    )
    table = (tmp_path / "bench.md").read_text()
    for label in (
        "runs reaching the stop criterion",
        "episodes to the study's criterion, all (demonstrations and random warm-up included)",
        "episodes to the study's criterion, learning only (without those)",
        "env steps to the study's criterion",
        "average reward at the stop (training, last 50 episodes)",
        "average reward of the selected policy (3 test runs)",
        "runs reaching the deployable criterion (97% of 100 validation runs)",
        "successful / collisions / no result",
        "mean time (s)",
        "reliability (%)",
        "reliability worst / median / best seed (%)",
        "reliability per seed (%)",
        "policy updates",
        "over seeds 100, 101",
        "wall-clock time (s)",
        "TD3 (ours)",
        "TD3 (study)",
        "PPO (ours)",
        "44268",
        "Potential-field controller",
    ):
        assert label in table
    data = json.loads((tmp_path / "bench.json").read_text())
    assert set(data["rows"]) == {"td3", "ppo"} and len(data["runs"]) == 4 and data["seeds"] == [100, 101]
    assert all(
        (tmp_path / "runs" / f"{a}-seed{s}" / "model.zip").is_file()
        for a in ("td3", "ppo")
        for s in (100, 101)
    )
    # 600 steps: the study's TD3 learns from its first transition (no random warm-up), one update per
    # step; PPO completes two rollouts of 512 steps and trains on each for 10 epochs
    assert [(r["algo"], r["updates"]) for r in data["runs"]] == [("td3", 600)] * 2 + [("ppo", 20)] * 2
    assert "reliability of behaviour cloning alone, before any PPO update (%)" in table
    # Run again: the finished runs are not trained again, the table is rebuilt from them.
    curve = tmp_path / "runs" / "td3-seed100" / "curve.csv"
    before = (curve.stat().st_mtime_ns, curve.read_text())
    (tmp_path / "bench.md").unlink()
    args = ["bench", "--algos", "td3", "ppo", "--seeds", "2", "--preset", "thesis", "--out", str(tmp_path)]
    args += ["--max-steps", "600", "--eval-episodes", "3", "--workers", "2", "--seed-offset", "100"]
    assert main(args) == 0
    assert (curve.stat().st_mtime_ns, curve.read_text()) == before
    assert (tmp_path / "bench.md").read_text() == table
    # A larger budget trains on the runs that did not meet their stop rule, from where they stopped.
    args[args.index("600")] = "900"
    assert main(args) == 0
    data = json.loads((tmp_path / "bench.json").read_text())
    assert [r["total_steps"] for r in data["runs"] if r["algo"] == "td3"] == [900, 900]
    assert curve.read_text().startswith(before[1]) and curve.read_text() != before[1]


@pytest.mark.slow
def test_ship_refuses_a_policy_below_95_percent(tmp_path: Path, monkeypatch: pytest.MonkeyPatch) -> None:
    from embedrl.train import ship

    monkeypatch.setattr(ship, "POLICIES", tmp_path / "policies")
    monkeypatch.setattr(ship, "SHIP_EPISODES", 5)
    train("td3", "thesis", 0, tmp_path / "run", SHORT)  # 600 steps: it cannot drive yet
    with pytest.raises(SystemExit, match=r"succeeds in .*% < 95%"):
        ship.ship(tmp_path / "run", "td3")
    assert not (tmp_path / "policies").exists()


def test_shipped_policies_meet_their_bar() -> None:
    """Every shipped policy is evaluated again, on the 200 seeds its metadata was measured on (seeds its
    training never used): it reproduces its recorded successes (within 2 episodes, for floating-point
    differences between CPUs) and the recorded rate meets the shipping bar."""
    import hashlib

    from embedrl.common import SHIP_TEST_SEED
    from embedrl.train.evaluate import evaluate
    from embedrl.train.scenarios import SCENARIOS
    from embedrl.train.ship import (
        MIN_SUCCESS,
        POLICIES,
        SHIP_EPISODES,
        WALKER_EPISODES,
        WALKER_MIN_SHARE,
        walking_episodes,
    )  # fmt: skip

    shipped = {
        p.parent.name: sorted(x.stem for x in p.parent.glob("*.json")) for p in POLICIES.glob("*/*.json")
    }
    assert shipped == {
        "static": ["ddpg", "ppo", "sac", "td3"],
        "moving-shelf": ["td3"],
        "two-robots": ["td3"],
        "walker": ["td3"],
    }
    for meta_file in sorted(POLICIES.glob("*/*.json")):
        scenario = meta_file.parent.name
        meta = json.loads(meta_file.read_text())
        model = meta_file.parent / meta["model"]
        assert hashlib.sha256(model.read_bytes()).hexdigest() == meta["sha256"]
        assert meta["config"].get("scenario", "static") == scenario
        recorded = meta["evaluation"]
        walker = scenario == "walker"  # the deck's gate: 90% of 50 walk 8 s without a fall at >= 1 m/s
        episodes = WALKER_EPISODES if walker else SHIP_EPISODES
        assert recorded["episodes"] == episodes
        assert (
            (meta["walking"]["share"] >= WALKER_MIN_SHARE)
            if walker
            else recorded["success_rate"] >= MIN_SUCCESS
        )
        assert recorded["seed"] == SHIP_TEST_SEED  # never a training seed
        assert recorded["env_id"] == SCENARIOS[scenario].env_id
        measured = evaluate(
            load_model_policy(model), episodes, SHIP_TEST_SEED, meta["model"],
            env_id=SCENARIOS[scenario].env_id, sample_time=SCENARIOS[scenario].sample_time_s,
        )  # fmt: skip
        assert abs(measured.successes - recorded["successes"]) <= 2, (meta["model"], measured.successes)
        if walker:
            assert abs(walking_episodes(measured) - meta["walking"]["without_fall_at_1_m_s"]) <= 2


@pytest.mark.slow
def test_ppo_warm_start_clones_the_baseline(tmp_path: Path) -> None:
    from embedrl.train.agents import build_model, make_env
    from embedrl.train.config import preset
    from embedrl.train.demonstrations import controller_demonstrations, warm_start
    from embedrl.train.potential_field import PotentialFieldController

    cfg = preset("ppo", "tuned")
    env = make_env(True, 0)
    model = build_model("ppo", cfg, env, 0, None)
    assert isinstance(model, PPO)
    obs, labels, _ = controller_demonstrations(20, 0.0, 7)  # held-out states of the baseline

    def error() -> float:
        x = env.normalize_obs(obs)  # type: ignore[attr-defined]
        return float(np.mean((model.predict(x, deterministic=True)[0] - labels) ** 2))

    before = error()
    warm_start(model, env, 100, 40, 0)
    assert error() < before / 5
    pf = PotentialFieldController()
    assert np.allclose(pf(obs[0]), labels[0])


def test_set_overrides_a_presets_hyperparameters_by_type() -> None:
    from embedrl.train.config import preset, with_overrides

    base = preset("td3", "tuned")
    changed = with_overrides(base, ["learning_rate=3e-4", "batch_size=64", "net_arch=64,32"])
    assert (changed.learning_rate, changed.batch_size, changed.net_arch) == (3e-4, 64, (64, 32))
    assert with_overrides(base, []) == base
    for bad, message in (
        ("learning_rat=1", "expected NAME=VALUE with NAME one of"),
        ("learning_rate", "expected NAME=VALUE"),
        ("batch_size=1.5", "--set batch_size=1.5: invalid literal"),
        ("learning_rate=nan", "not a finite number"),
        ("learning_rate=0", r"--set learning_rate=0.0: must be > 0"),
        ("tau=2", r"--set tau=2.0: must be in \(0, 1\]"),
        ("gamma=1.5", r"must be in \(0, 1\]"),
        ("noise_sigma=-0.1", "must be >= 0"),
        ("batch_size=0", "must be at least 1"),
        ("net_arch=64,0", "every size must be at least 1"),
    ):
        with pytest.raises(ValueError, match=message):
            with_overrides(base, [bad])
    assert with_overrides(base, ["gamma=1", "noise_sigma=0"]).gamma == 1.0  # the closed ends are allowed


@pytest.mark.training
def test_set_is_recorded_in_the_runs_config_and_bad_names_exit_2(
    tmp_path: Path, capsys: pytest.CaptureFixture[str]
) -> None:
    argv = ["train", "--algo", "sac", "--preset", "thesis", "--max-steps", "300", "--eval-every", "1000"]
    assert (
        main([*argv, "--set", "learning_rate=5e-4", "--set", "batch_size=32", "--out", str(tmp_path / "r")])
        == 0
    )
    config = json.loads((tmp_path / "r" / "config.json").read_text())
    assert config["overrides"] == ["learning_rate=5e-4", "batch_size=32"]
    assert (
        config["hyperparameters"]["learning_rate"] == 5e-4 and config["hyperparameters"]["batch_size"] == 32
    )
    assert main([*argv, "--set", "gama=0.9", "--out", str(tmp_path / "bad")]) == 2
    assert "expected NAME=VALUE with NAME one of" in capsys.readouterr().err
    assert not (tmp_path / "bad").exists()


@pytest.mark.slow
def test_a_run_ships_its_best_validated_checkpoint(tmp_path: Path) -> None:
    run = tmp_path / "run"
    budget = Budget(max_steps=1200, eval_every=300, eval_episodes=5, stop="budget", checkpoint_every=600)
    summary = train("td3", "tuned", 0, run, budget, overrides=["learning_starts=300", "demonstrations=2"])
    assert summary["selected"] == "best validation" and summary["best_validation"]["step"] % 300 == 0
    assert (run / "model.zip").read_bytes() == (run / "best_model.zip").read_bytes()
    assert (run / "last_model.zip").is_file() and summary["total_steps"] == 1200
    with (run / "evaluations.csv").open() as f:
        rows = list(csv.DictReader(f))
    assert [int(r["steps"]) for r in rows] == [300, 600, 900, 1200]
    trained = [r for r in rows if int(r["steps"]) > 300]  # at step 300 the warm-up has just ended
    best = max(trained, key=lambda r: (float(r["success_rate"]), float(r["mean_return"])))
    assert int(best["steps"]) == summary["best_validation"]["step"]


@pytest.mark.slow
def test_portable_training_repeats_whatever_instructions_the_cpu_offers(tmp_path: Path) -> None:
    """The same run with MKL restricted to SSE4.2 (an older CPU) and unrestricted: identical with
    --portable; the run records the CPU it used."""
    import os
    import subprocess
    import sys

    from stable_baselines3 import TD3

    def run(name: str, instructions: str | None) -> np.ndarray:
        env = {k: v for k, v in os.environ.items() if k not in ("MKL_CBWR", "ATEN_CPU_CAPABILITY")}
        if instructions:
            env["MKL_ENABLE_INSTRUCTIONS"] = instructions
        args = ["train", "--portable", "--out", str(tmp_path / name), "--max-steps", "1500"]
        args += [
            "--stop",
            "budget",
            "--set",
            "learning_starts=500",
            "--set",
            "demonstrations=2",
            "--eval-every",
            "100000",
        ]
        subprocess.run([sys.executable, "-m", "embedrl.cli", *args], env=env, check=True, capture_output=True)
        config = json.loads((tmp_path / name / "config.json").read_text())
        assert config["machine"]["portable"] and config["machine"]["torch_cpu_capability"] == "DEFAULT"
        assert config["machine"]["cpu"] and config["machine"]["MKL_CBWR"] == "COMPATIBLE"
        model = TD3.load(tmp_path / name / "model.zip", device="cpu")
        obs = np.random.default_rng(0).uniform(-1, 1, (256, 6)).astype(np.float32)
        return np.asarray(model.predict(obs, deterministic=True)[0])

    np.testing.assert_array_equal(run("any", None), run("sse42", "SSE4_2"))
    assert (tmp_path / "any" / "curve.csv").read_text() == (tmp_path / "sse42" / "curve.csv").read_text()


@pytest.mark.slow
def test_a_resume_with_nothing_left_to_train_keeps_the_step_count(tmp_path: Path) -> None:
    """Resuming at a budget the run already met trains nothing and leaves its checkpoint as it was: a later
    resume to a larger budget trains only the difference."""
    run = tmp_path / "run"
    first = ["--max-steps", "1100", "--checkpoint-every", "500", "--eval-every", "100000", "--stop", "budget"]
    assert main(["train", "--algo", "ppo", "--seed", "2", *first, "--out", str(run)]) == 0
    assert json.loads((run / "summary.json").read_text())["total_steps"] == 2048  # two rollouts of 1024
    assert main(["train", "--resume", str(run), "--max-steps", "1700"]) == 0
    assert json.loads((run / "checkpoint" / "state.json").read_text())["steps"] == 2048
    assert main(["train", "--resume", str(run), "--max-steps", "4000"]) == 0
    assert json.loads((run / "summary.json").read_text())["total_steps"] == 4096
