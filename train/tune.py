"""``embedrl tune``: a hyperparameter search with Optuna over one algorithm's preset in one scenario.

Each trial trains a run from a preset with the sampled changes (Optuna's TPE sampler, seeded) for a fixed
budget, in :data:`RUNGS` steps; after each, its selected model is evaluated on the validation seeds (never
the test seeds) and the success rate is reported, so Optuna's median pruner can stop a trial that is behind
the others at the same step. The study lives in ``DIR/study.db`` (SQLite): an interrupted search goes on
where it stopped, with fresh suggestions (the sampler is seeded with the seed plus the trials so far); a
trial a killed search left running is marked failed, and failed trials do not count towards ``--trials``.
One search at a time works in a folder (a lock on ``study.db``). The best trial is written as a preset
file (``DIR/best_preset.json``) that ``embedrl train --preset FILE`` reads, with the trials' table
(``DIR/trials.md``); ``"untrained": true`` in it says that the trials' budget ended within the random
warm-up, so that no trial trained at all.
"""

from __future__ import annotations

import contextlib
import fcntl
import os
from collections.abc import Callable, Iterator
from dataclasses import dataclass
from pathlib import Path
from typing import Any

from embedrl.common import VALIDATION_SEED, on_terminal, read_json, write_json
from embedrl.train.errors import UsageError

RUNGS = 3
"""Evaluations per trial (at 1/3, 2/3 and all of the budget): what the pruner compares."""
VALIDATION_EPISODES = 50
"""Episodes of each evaluation, seeded from ``VALIDATION_SEED``."""
SPACE: dict[str, tuple[str, Any]] = {
    "learning_rate": ("log", (1e-4, 3e-3)),
    "gamma": ("choice", (0.98, 0.99, 0.995)),
    "batch_size": ("choice", (64, 128, 256)),
    "tau": ("log", (1e-3, 2e-2)),
    "noise_sigma": ("float", (0.05, 0.4)),
}
"""What a trial may change, where the preset has the field: the scale and the range or the choices."""


def sample(trial: Any, fields: set[str]) -> list[str]:
    """The trial's changes as ``--set`` assignments, for the fields the algorithm's config has."""
    changes = []
    for name, (kind, spec) in SPACE.items():
        if name not in fields:
            continue
        if kind == "choice":
            value = trial.suggest_categorical(name, list(spec))
        else:
            value = trial.suggest_float(name, spec[0], spec[1], log=kind == "log")
        changes.append(f"{name}={value}")
    return changes


@dataclass(frozen=True)
class Search:
    """What a search trains: one algorithm's preset in one scenario, each trial for ``max_steps``."""

    algo: str
    scenario: str
    max_steps: int
    out: Path
    seed: int = 0
    base: str = "tuned"

    @property
    def name(self) -> str:
        return f"{self.algo}-{self.scenario}"

    @property
    def storage(self) -> str:
        return f"sqlite:///{self.out.resolve() / 'study.db'}"


Optimize = Callable[["Search", set[str], int], None]
"""Runs ``n`` more trials of a search whose configs have the given fields, recording them in its study
(:func:`embedrl.train.tune_ray.optimize_on_ray`)."""


def run_tune(search: Search, trials: int, optimize: Optimize | None = None) -> dict[str, Any]:
    """Run (or continue) the search until ``trials`` have finished, one after another here or by
    ``optimize``; the best trial as a preset file's content."""
    import optuna

    from embedrl.train.config import preset, to_dict, untrained_budget, with_overrides

    search.out.mkdir(parents=True, exist_ok=True)
    fields = set(to_dict(preset(search.algo, search.base, search.scenario)))
    optuna.logging.set_verbosity(optuna.logging.WARNING)
    with _only_search(search):
        study = optuna.create_study(
            study_name=search.name, storage=search.storage, load_if_exists=True, direction="maximize",
            pruner=optuna.pruners.MedianPruner(n_startup_trials=2, n_warmup_steps=0),
        )  # fmt: skip
        fail_stale_trials(study, search)
        study.sampler = sampler(search, len(study.trials))
        left = trials - len(counted(study.trials))
        if left > 0 and optimize is not None:
            optimize(search, fields, left)
            study = optuna.load_study(study_name=search.name, storage=search.storage)
        elif left > 0:
            study.optimize(lambda trial: _objective(trial, search, fields), n_trials=left,
                           show_progress_bar=on_terminal())  # fmt: skip
    best = _best(study)
    overrides = overrides_of(best.params)
    idle = untrained_budget(with_overrides(preset(search.algo, search.base, search.scenario), overrides),
                            search.max_steps)  # fmt: skip
    result = {
        "algo": search.algo, "scenario": search.scenario, "base_preset": search.base,
        "overrides": overrides, "validation_success": best.value, "trial": best.number,
        "max_steps": search.max_steps, "seed": search.seed, "untrained": idle is not None,
    }  # fmt: skip
    write_json(result, search.out / "best_preset.json")
    (search.out / "trials.md").write_text(_table(study))
    return result


@contextlib.contextmanager
def _only_search(search: Search) -> Iterator[None]:
    """Hold a lock on ``DIR/study.db`` (beside SQLite's own locks): one search at a time in a folder, so
    that a trial left running in the study is a stale one (its search was killed), never another's."""
    database = search.out / "study.db"
    database.touch()
    fd = os.open(database, os.O_RDONLY)
    try:
        try:
            fcntl.flock(fd, fcntl.LOCK_EX | fcntl.LOCK_NB)
        except BlockingIOError:
            raise UsageError(f"another `embedrl tune` is searching in {search.out}; wait for it") from None
        yield
    finally:
        os.close(fd)


def fail_stale_trials(study: Any, search: Search) -> None:
    """Mark the trials a killed search left running as failed (they never end otherwise)."""
    import optuna

    storage = optuna.storages.RDBStorage(search.storage)
    study_id = storage.get_study_id_from_name(search.name)
    for t in study.get_trials(deepcopy=False, states=(optuna.trial.TrialState.RUNNING,)):
        trial_id = storage.get_trial_id_from_study_id_trial_number(study_id, t.number)
        storage.set_trial_state_values(trial_id, optuna.trial.TrialState.FAIL)


def sampler(search: Search, known: int) -> Any:
    """The TPE sampler of a search whose study holds ``known`` trials: seeded with the search's seed plus
    ``known``, so that a resumed search does not suggest its first trials' values again (the sampler's
    random start would repeat them from the same seed)."""
    import optuna

    return optuna.samplers.TPESampler(seed=search.seed + known)


def counted(trials: list[Any]) -> list[Any]:
    """The trials that count towards ``--trials``: complete or pruned, not failed (interrupted, killed)."""
    import optuna

    finished = (optuna.trial.TrialState.COMPLETE, optuna.trial.TrialState.PRUNED)
    return [t for t in trials if t.state in finished]


def overrides_of(params: dict[str, Any]) -> list[str]:
    """A trial's sampled values as ``--set`` assignments, in :data:`SPACE`'s order."""
    return [f"{name}={params[name]}" for name in SPACE if name in params]


def train_trial(
    search: Search, overrides: list[str], run: Path, report: Callable[[float, int], bool]
) -> float:
    """Train one trial in :data:`RUNGS` steps, evaluating the selected model on the validation seeds after
    each; ``report(success, steps)`` returns True when the trial should stop there. The last success."""
    from embedrl.train.config import Budget
    from embedrl.train.evaluate import evaluate
    from embedrl.train.models import load_model_policy
    from embedrl.train.scenarios import SCENARIOS
    from embedrl.train.trainer import train

    success = 0.0
    for rung in range(1, RUNGS + 1):
        steps = search.max_steps * rung // RUNGS
        budget = Budget(max_steps=steps, stop="budget", eval_every=max(steps // 4, 100), eval_episodes=20)
        train(search.algo, search.base, search.seed, run, budget, resume=rung > 1,
              overrides=() if rung > 1 else overrides, scenario=search.scenario)  # fmt: skip
        report_ = evaluate(load_model_policy(run / "model.zip"), VALIDATION_EPISODES, VALIDATION_SEED,
                           run.name, env_id=SCENARIOS[search.scenario].env_id)  # fmt: skip
        success = report_.success_rate
        if report(success, steps):
            break
    return success


def _objective(trial: Any, search: Search, fields: set[str]) -> float:
    import optuna

    def report(success: float, steps: int) -> bool:
        trial.report(success, steps)
        if trial.should_prune():
            raise optuna.TrialPruned()
        return False

    overrides = sample(trial, fields)
    return train_trial(search, overrides, search.out / "trials" / f"trial-{trial.number}", report)


def _best(study: Any) -> Any:
    """The best trial that trained its whole budget (on Ray a stopped trial is recorded as complete with
    the value it had when stopped)."""
    import optuna

    whole = [
        t for t in study.trials
        if t.state == optuna.trial.TrialState.COMPLETE and len(t.intermediate_values) == RUNGS
    ]  # fmt: skip
    if not whole:
        raise RuntimeError("no trial trained its whole budget: run more trials")
    return max(whole, key=lambda t: (t.value, -t.number))


def _table(study: Any) -> str:
    lines = ["| trial | state | validation success | evaluations | changes |", "|---|---|---|---|---|"]
    for t in study.trials:
        value = "-" if t.value is None else f"{100 * t.value:.0f}%"
        last = f"{len(t.intermediate_values)}/{RUNGS}"
        lines.append(f"| {t.number} | {t.state.name.lower()} | {value} | {last} | "
                     f"{', '.join(overrides_of(t.params))} |")  # fmt: skip
    return "\n".join(lines) + "\n"


def read_preset_file(path: Path) -> tuple[str, list[str]]:
    """A preset file (``embedrl tune``'s ``best_preset.json``): its base preset and its changes."""
    from embedrl.train.config import PRESETS

    try:
        data = read_json(path)
        base, overrides = data["base_preset"], data["overrides"]
    except (OSError, ValueError, KeyError, TypeError) as exc:
        raise ValueError(f"{path}: not a preset file of `embedrl tune` ({exc})") from None
    if (
        base not in PRESETS
        or not isinstance(overrides, list)
        or not all(isinstance(o, str) for o in overrides)
    ):
        raise ValueError(f"{path}: not a preset file of `embedrl tune` (base_preset, overrides)")
    return base, overrides
