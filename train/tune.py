"""``embedrl tune``: a hyperparameter search with Optuna over one algorithm's preset in one scenario.

Each trial trains a run from a preset with the sampled changes (Optuna's TPE sampler, seeded) for a fixed
budget, in :data:`RUNGS` steps; after each, its selected model is evaluated on the validation seeds (never
the test seeds) and the success rate is reported, so Optuna's median pruner can stop a trial that is behind
the others at the same step. The study lives in ``DIR/study.db`` (SQLite): an interrupted search goes on
where it stopped. The best trial is written as a preset file (``DIR/best_preset.json``) that ``embedrl
train --preset FILE`` reads, with the trials' table (``DIR/trials.md``).
"""

from __future__ import annotations

import json
import sys
from pathlib import Path
from typing import Any

from embedrl.common import VALIDATION_SEED, write_json

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


def run_tune(
    algo: str, scenario: str, trials: int, max_steps: int, out: Path, seed: int = 0, base: str = "tuned"
) -> dict[str, Any]:
    """Run (or continue) the search; the best trial as a preset file's content."""
    import optuna

    from embedrl.train.config import preset, to_dict

    out.mkdir(parents=True, exist_ok=True)
    fields = set(to_dict(preset(algo, base, scenario)))
    optuna.logging.set_verbosity(optuna.logging.WARNING)
    study = optuna.create_study(
        study_name=f"{algo}-{scenario}", storage=f"sqlite:///{out / 'study.db'}", load_if_exists=True,
        direction="maximize", sampler=optuna.samplers.TPESampler(seed=seed),
        pruner=optuna.pruners.MedianPruner(n_startup_trials=2, n_warmup_steps=0),
    )  # fmt: skip
    left = trials - len([t for t in study.trials if t.state.is_finished()])
    if left > 0:
        study.optimize(
            lambda trial: _objective(trial, algo, scenario, max_steps, out, seed, base, fields),
            n_trials=left, show_progress_bar=sys.stderr.isatty(),
        )  # fmt: skip
    best = study.best_trial
    result = {
        "algo": algo, "scenario": scenario, "base_preset": base, "overrides": best.user_attrs["overrides"],
        "validation_success": best.value, "trial": best.number, "max_steps": max_steps, "seed": seed,
    }  # fmt: skip
    write_json(result, out / "best_preset.json")
    (out / "trials.md").write_text(_table(study))
    return result


def _objective(
    trial: Any, algo: str, scenario: str, max_steps: int, out: Path, seed: int, base: str, fields: set[str]
) -> float:
    import optuna

    from embedrl.train.config import Budget
    from embedrl.train.evaluate import evaluate
    from embedrl.train.models import load_model_policy
    from embedrl.train.scenarios import SCENARIOS
    from embedrl.train.trainer import train

    overrides = sample(trial, fields)
    trial.set_user_attr("overrides", overrides)
    run = out / "trials" / f"trial-{trial.number}"
    success = 0.0
    for rung in range(1, RUNGS + 1):
        steps = max_steps * rung // RUNGS
        budget = Budget(max_steps=steps, stop="budget", eval_every=max(steps // 4, 100), eval_episodes=20)
        train(algo, base, seed, run, budget, resume=rung > 1, overrides=() if rung > 1 else overrides,
              scenario=scenario)  # fmt: skip
        report = evaluate(load_model_policy(run / "model.zip"), VALIDATION_EPISODES, VALIDATION_SEED,
                          f"trial {trial.number}", env_id=SCENARIOS[scenario].env_id)  # fmt: skip
        success = report.success_rate
        trial.report(success, steps)
        if trial.should_prune():
            raise optuna.TrialPruned()
    return success


def _table(study: Any) -> str:
    lines = ["| trial | state | validation success | last step | changes |", "|---|---|---|---|---|"]
    for t in study.trials:
        value = "-" if t.value is None else f"{100 * t.value:.0f}%"
        last = max(t.intermediate_values, default="-")
        lines.append(f"| {t.number} | {t.state.name.lower()} | {value} | {last} | "
                     f"{', '.join(t.user_attrs.get('overrides', []))} |")  # fmt: skip
    return "\n".join(lines) + "\n"


def read_preset_file(path: Path) -> tuple[str, list[str]]:
    """A preset file (``embedrl tune``'s ``best_preset.json``): its base preset and its changes."""
    from embedrl.train.config import PRESETS

    try:
        data = json.loads(path.read_text())
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
