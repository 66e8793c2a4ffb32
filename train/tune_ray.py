"""``embedrl tune --ray``: the same search with its trials run by Ray Tune, on this machine or a cluster.

Optuna still samples (Ray Tune's ``OptunaSearch`` with the seeded TPE sampler, on the study in
``DIR/study.db``, so the table, the best preset and a resumed search are the same as without Ray). Optuna's
pruner cannot run inside Ray Tune; Ray Tune's median stopping rule takes its place: after each evaluation a
trial whose best validation success is below the median of the other trials at the same evaluation is
stopped, from the second evaluation of at least two other trials on. Each trial declares one CPU. Ray Tune's
own records go to ``DIR/ray``.
"""

from __future__ import annotations

import dataclasses
from pathlib import Path
from typing import Any

from embedrl.common import on_terminal
from embedrl.train.sweep import CPUS_PER_RUN
from embedrl.train.tune import SPACE, Search, overrides_of, sampler, train_trial

METRIC = "success"
"""The metric each trial reports after each evaluation: the validation success rate."""


def optimize_on_ray(search: Search, fields: set[str], trials: int, *, address: str, workers: int) -> None:
    """Run ``trials`` more trials of ``search`` on Ray (``address``: ``local``, ``auto`` or ``HOST:PORT``;
    ``workers`` trials at once on a local instance); they are recorded in the Optuna study as they end."""
    import optuna
    import ray
    from ray import tune
    from ray.tune.search.optuna import OptunaSearch

    search = dataclasses.replace(search, out=search.out.resolve())  # trials run in folders of Ray's
    local = address == "local"
    if not ray.is_initialized():
        ray.init(address=None if local else address, num_cpus=workers if local else None,
                 include_dashboard=False, log_to_driver=False, configure_logging=False)  # fmt: skip
    known = len(optuna.load_study(study_name=search.name, storage=search.storage).trials)
    searcher = OptunaSearch(
        metric=METRIC, mode="max", sampler=sampler(search, known),
        study_name=search.name, storage=optuna.storages.RDBStorage(search.storage),
    )  # fmt: skip
    stopper = _median_rule()
    trainable = tune.with_resources(tune.with_parameters(_trial, search=search), {"cpu": CPUS_PER_RUN})
    tuner = tune.Tuner(
        trainable, param_space=_space(fields),
        tune_config=tune.TuneConfig(metric=METRIC, mode="max", search_alg=searcher, scheduler=stopper,
                                    num_samples=trials, max_concurrent_trials=workers if local else None),
        run_config=tune.RunConfig(name=search.name, storage_path=str(search.out / "ray"), verbose=0,
                                  callbacks=[_progress_callback(trials)]),
    )  # fmt: skip
    try:
        tuner.fit()
    finally:
        if local:
            ray.shutdown()


def _progress_callback(total: int) -> Any:
    """A Ray Tune callback drawing a bar of finished trials (Ray Tune's own tables are turned off)."""
    from ray.tune import Callback
    from tqdm import tqdm

    class Progress(Callback):
        bar: Any = None  # made at the first trial: Ray Tune pickles its callbacks with the experiment

        def __getstate__(self) -> dict[str, Any]:
            return {}

        def on_trial_start(self, iteration: int, trials: list[Any], trial: Any, **info: Any) -> None:
            if self.bar is None:
                self.bar = tqdm(total=total, desc="trials", unit="trial", disable=not on_terminal())

        def on_trial_complete(self, iteration: int, trials: list[Any], trial: Any, **info: Any) -> None:
            self.bar.update()

        def on_trial_error(self, iteration: int, trials: list[Any], trial: Any, **info: Any) -> None:
            self.bar.write(f"failed: trial {trial.trial_id}: see {search_error_file(trial)}")
            self.bar.update()

        def on_experiment_end(self, trials: list[Any], **info: Any) -> None:
            if self.bar is not None:
                self.bar.close()

    return Progress()


def search_error_file(trial: Any) -> str:
    """Where Ray Tune put a failed trial's traceback."""
    return str(getattr(trial, "error_file", None) or "Ray's logs")


def _median_rule() -> Any:
    """Ray Tune's median stopping rule, except that it never pauses a trial to let a pending one run while
    too few trials have results to compare (a paused trial would start again from scratch)."""
    from ray.tune.schedulers import MedianStoppingRule, TrialScheduler

    class MedianRule(MedianStoppingRule):
        def _on_insufficient_samples(self, tune_controller: Any, trial: Any, time: float) -> str:
            return str(TrialScheduler.CONTINUE)

    return MedianRule(time_attr="training_iteration", grace_period=2, min_samples_required=2)


def _space(fields: set[str]) -> dict[str, Any]:
    """:data:`SPACE` in Ray Tune's terms, for the fields the algorithm's config has."""
    from ray import tune

    space: dict[str, Any] = {}
    for name, (kind, spec) in SPACE.items():
        if name not in fields:
            continue
        if kind == "choice":
            space[name] = tune.choice(list(spec))
        else:
            space[name] = (tune.loguniform if kind == "log" else tune.uniform)(spec[0], spec[1])
    return space


def _trial(config: dict[str, Any], search: Search) -> None:
    """One Ray Tune trial: trains in its own folder ``DIR/trials/ray-<trial id>``, reports each evaluation."""
    from ray import tune

    run = search.out.resolve() / "trials" / f"ray-{tune.get_context().get_trial_id()}"

    def report(success: float, steps: int) -> bool:
        tune.report({METRIC: success, "steps": steps})
        return False  # Ray Tune stops a trial at a report itself

    train_trial(search, overrides_of(config), Path(run), report)
