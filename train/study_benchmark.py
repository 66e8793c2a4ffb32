"""``embedrl bench``: K seeds per algorithm trained in parallel, the reference study's table.

Each run trains until its stop rule (or the budget), then its selected model is evaluated
deterministically on seeds it was not trained on. A run that finished before (its ``summary.json``) is not
trained again and one that was interrupted is resumed, so an interrupted bench goes on where it stopped.
Per algorithm the table gives the median over seeds with a 95% bootstrap interval (from three seeds), and
the study's numbers beside ours; the potential-field controller is evaluated on the same seeds. The runs go
to a process pool or to Ray (:mod:`embedrl.train.sweep`); each writes ``result.json`` in its folder as it
ends, so the table can be rebuilt from the folders (``--from``).
"""

from __future__ import annotations

import json
import textwrap
from dataclasses import replace
from pathlib import Path
from typing import Any

import numpy as np

from embedrl.common import BENCH_TEST_SEED, provenance, write_json
from embedrl.train.config import ALGOS, Budget
from embedrl.train.evaluate import REPORT_KEYS, evaluate
from embedrl.train.scenarios import DEFAULT_SCENARIO, MOVING_SHELF, STATIC, TEACHERS, TWO_ROBOTS
from embedrl.train.sweep import Failure, run_all

BOOTSTRAP_SAMPLES = 2000
ALGO_ORDER = ALGOS
"""The table's column order."""

STUDY = {
    "ddpg": {
        "episodes": 17135,
        "average_reward": 2.0094,
        "outcomes": "197 / 3 / 0",
        "mean_time_s": 6.93,
        "reliability": 99.0,  # as the study prints it (197 / 200 is 98.5%)
    },
    "td3": {
        "episodes": 44268,
        "average_reward": 2.0648,
        "outcomes": "147 / 42 / 11",
        "mean_time_s": 7.23,
        "reliability": 73.5,
    },
    "sac": {
        "episodes": 7618,
        "average_reward": 2.0477,
        "outcomes": "104 / 96 / 0",
        "mean_time_s": 7.06,
        "reliability": 52.0,
    },
    "ppo": {
        "episodes": "100,000 (never)",
        "average_reward": -0.0005,
        "outcomes": "102 / 98 / 0",
        "mean_time_s": 7.39,
        "reliability": 51.0,
    },
}
"""The reference study's table for the static scenario (MATLAB, 200 evaluation runs each). Its "average
reward" is the training average at the stop, not an evaluation."""

STUDY_BY_SCENARIO: dict[str, dict[str, dict[str, Any]]] = {
    STATIC.name: STUDY,
    MOVING_SHELF.name: {
        "ddpg": {
            "episodes": "80,000+ (never)",
            "outcomes": "184 / 16 / 0",
            "mean_time_s": 7.92,
            "reliability": 92.0,
        },
    },
    TWO_ROBOTS.name: {
        "ddpg": {
            "episodes": "never (+20: peaks of 96 and 83 successes, then 0; +5: never learned)",
            "outcomes": "unstable, then collapse",
        },
    },
}
"""The study's results per scenario: only DDPG was run on the moving shelf and the two robots, and the
study reports the two-robot runs as curves, not as a 200-run evaluation."""


Job = tuple[str, str, int, str, int, int, str, tuple[str, ...], str | None, tuple[int, int] | None]
"""algo, preset, seed, run directory, max steps, test episodes, scenario, overrides, stop rule (None: the
study's criterion for ``thesis``, the deployable one for ``tuned``), validation (env steps between
validation evaluations and episodes in each; None: :class:`Budget`'s)."""


def one_run(job: Job) -> dict[str, Any]:
    """Train one run (or take it as it finished, or resume it) and evaluate its selected model."""
    algo, preset, seed, out, max_steps, eval_episodes, scenario, overrides, stop, validation = job
    from embedrl.train.models import load_model_policy
    from embedrl.train.scenarios import SCENARIOS
    from embedrl.train.trainer import train

    run = Path(out)
    # The study's protocol stops at its criterion; tuned runs stop at the deployable one (validation).
    budget = Budget(max_steps=max_steps, stop=stop or ("study" if preset == "thesis" else "validation"))
    if validation is not None:
        budget = replace(budget, eval_every=validation[0], eval_episodes=validation[1])
    if _finished(run, budget):  # an interrupted bench goes on, a table is rebuilt
        summary = {**_derived(run), **json.loads((run / "summary.json").read_text())}
    else:  # new, interrupted, or stopped at a smaller budget without meeting its stop rule: trained on
        resume = (run / "config.json").is_file()
        summary = train(
            algo, preset, seed, run, budget, resume=resume, scenario=scenario, overrides=overrides
        )
    report = evaluate(
        load_model_policy(run / "model.zip"),
        eval_episodes,
        BENCH_TEST_SEED,
        f"{algo} seed {seed}",
        env_id=SCENARIOS[scenario].env_id,
    )
    cloned = None
    if (run / "warm_start_model.zip").is_file():  # PPO: what behaviour cloning alone gives, on the same seeds
        alone = evaluate(
            load_model_policy(run / "warm_start_model.zip"),
            eval_episodes,
            BENCH_TEST_SEED,
            f"{algo} seed {seed} warm start",
            env_id=SCENARIOS[scenario].env_id,
        )
        cloned = {k: getattr(alone, k) for k in REPORT_KEYS}
    result = {
        **summary,
        "run": str(run),
        "max_steps": max_steps,
        "evaluation": {
            **{k: getattr(report, k) for k in REPORT_KEYS},
            "mean_steps": report.mean_steps,
            **report.walking(),
        },
        "warm_start_evaluation": cloned,
    }
    write_json(result, run / RESULT_FILE)  # as each run ends: the table can be rebuilt from the folders
    return result


RESULT_FILE = "result.json"
"""A finished run's summary and evaluation, in its folder (``embedrl bench --from`` reads them)."""


def _finished(run: Path, budget: Budget) -> bool:
    """Whether a run is done for this budget: it has a summary, and it met its stop rule or trained as
    long as the budget allows."""
    if not (run / "summary.json").is_file():
        return False
    summary = json.loads((run / "summary.json").read_text())
    stopped = (budget.stop == "study" and summary["criterion_reached"]) or (
        budget.stop == "validation" and summary.get("validation_target_step") is not None
    )
    return bool(
        stopped
        or summary["total_steps"] >= budget.max_steps
        or summary["total_episodes"] >= budget.max_episodes
    )


def _derived(run: Path) -> dict[str, Any]:
    """What a run's summary holds about its curve and its demonstrations, from its files (for runs whose
    summary predates these keys)."""
    import csv

    from embedrl.train.monitor import STOP_WINDOW

    hyper = json.loads((run / "config.json").read_text())["hyperparameters"]
    with (run / "curve.csv").open() as f:
        rows = list(csv.DictReader(f))
    returns = [float(r["return"]) for r in rows]
    warmup = int(hyper.get("learning_starts", 0))
    return {
        "average50_at_stop": float(np.mean(returns[-STOP_WINDOW:])) if returns else None,
        "warmup_episodes": sum(int(r["steps"]) <= warmup for r in rows),
        "demonstration_episodes": int(hyper.get("demonstrations", hyper.get("warm_start_demonstrations", 0))),
    }


def run_jobs(
    jobs: list[Job], workers: int, ray: str | None = None
) -> tuple[list[dict[str, Any]], list[Failure]]:
    """Every job's result (those that failed left out, in order) and the failures
    (:func:`embedrl.train.sweep.run_all`: this process, a process pool or Ray)."""
    results, failures = run_all(one_run, jobs, workers, ray, label=lambda job: f"{job[0]} seed {job[2]}")
    return [r for r in results if r is not None], failures


def median_ci(values: list[float]) -> tuple[float, float | None, float | None]:
    """Median and its 95% bootstrap interval (scipy's BCa bootstrap, seeded); no interval below
    :data:`MIN_SEEDS_FOR_INTERVAL` values or when every value is the same."""
    from scipy.stats import bootstrap

    data = np.asarray(values, dtype=float)
    median = float(np.median(data))
    if len(data) < MIN_SEEDS_FOR_INTERVAL or np.all(data == data[0]):
        return median, None, None
    ci = bootstrap((data,), np.median, n_resamples=BOOTSTRAP_SAMPLES, confidence_level=0.95,
                   method="percentile", rng=np.random.default_rng(0)).confidence_interval  # fmt: skip
    return median, float(ci.low), float(ci.high)


MIN_SEEDS_FOR_INTERVAL = 3
"""Fewer values than this give a median without an interval (two points bound nothing)."""


def _cell(values: list[float], fmt: str) -> str:
    if not values:
        return "-"
    m, lo, hi = median_ci(values)
    return f"{m:{fmt}}" if lo is None or hi is None else f"{m:{fmt}} [{lo:{fmt}}, {hi:{fmt}}]"


def run_bench(
    algos: list[str],
    seeds: int,
    preset: str,
    out: Path,
    max_steps: int,
    eval_episodes: int,
    workers: int,
    seed_offset: int = 0,
    scenario: str = DEFAULT_SCENARIO,
    overrides: tuple[str, ...] = (),
    ray: str | None = None,
) -> tuple[str, list[Failure]]:
    """Train seeds ``seed_offset .. seed_offset + seeds - 1`` of each algorithm on ``scenario``; the table
    (also written) and the runs that failed."""
    seed_list = list(range(seed_offset, seed_offset + seeds))
    jobs: list[Job] = [
        (
            a,
            preset,
            s,
            str(out / "runs" / f"{a}-seed{s}"),
            max_steps,
            eval_episodes,
            scenario,
            overrides,
            None,
            None,
        )
        for a in algos
        for s in seed_list
    ]
    runs, failures = run_jobs(jobs, workers, ray)
    note = (
        f"preset `{preset}`"
        + (f" with {', '.join(overrides)}" if overrides else "")
        + f", budget {max_steps} steps"
    )
    failed = [f"{f.job[0]} seed {f.job[2]}: {f.error}" for f in failures]
    return write_table(runs, out, note, failed), failures


def table_from(folders: list[Path], out: Path) -> str:
    """The table again from finished runs (``runs/*/result.json`` under each of ``folders``, as a bench on
    any machine of a cluster wrote them, or a run folder's own ``result.json``), written into ``out``."""
    from embedrl.common import read_json

    found = []
    for folder in folders:
        own = folder / RESULT_FILE
        found += [own] if own.is_file() else sorted(folder.glob(f"runs/*/{RESULT_FILE}"))
    runs = [read_json(p) for p in found]
    for path, run in zip(found, runs, strict=True):
        _check_result(path, run)
    if not runs:
        raise ValueError(
            f"no finished runs ({RESULT_FILE} or runs/*/{RESULT_FILE}) under {', '.join(map(str, folders))}"
        )
    presets = sorted({r["preset"] for r in runs})
    steps = sorted({r.get("max_steps", r["total_steps"]) for r in runs})
    budgets = ", ".join(map(str, steps))
    named = ", ".join(f"`{p}`" for p in presets)
    note = f"preset {named}, budget {budgets} steps, from {len(runs)} run folders"
    return write_table(runs, out, note, [])


NUMBER = (int, float)
OPTIONAL_COUNT = (int, type(None))
RESULT_KEYS: dict[str, tuple[type, ...]] = {
    "algo": (str,), "preset": (str,), "scenario": (str,), "seed": (int,), "run": (str,),
    "total_steps": (int,), "criterion_reached": (bool,), "evaluation": (dict,),
    "episodes_to_criterion": OPTIONAL_COUNT, "steps_to_criterion": OPTIONAL_COUNT,
    "demonstration_episodes": (int,), "warmup_episodes": (int,), "validation_target_step": OPTIONAL_COUNT,
    "average50_at_stop": (*NUMBER, type(None)), "updates": (int,), "wall_clock_s": NUMBER,
}  # fmt: skip
"""What the table reads of each run's result.json, and its types."""
EVALUATION_KEYS: dict[str, tuple[type, ...]] = {
    "episodes": (int,), "successes": (int,), "collisions": (int,), "timeouts": (int,),
    "success_rate": NUMBER, "mean_return": NUMBER, "mean_time_s": (*NUMBER, type(None)),
}  # fmt: skip


def _check_result(path: Path, result: Any) -> None:
    """A run's result.json as the table reads it (``bench --from`` takes them from anywhere): ValueError
    naming the file and the first key missing or of another type, or the run folder's missing curve."""

    def check(data: dict[str, Any], keys: dict[str, tuple[type, ...]], prefix: str) -> None:
        for key, kinds in keys.items():
            value = data.get(key, ...)
            wrong = not isinstance(value, kinds) or (isinstance(value, bool) and bool not in kinds)
            if value is ... or wrong:
                shown = "missing" if value is ... else f"{value!r}"
                raise ValueError(f"{path}: not a bench result ({prefix}{key} is {shown})")

    if not isinstance(result, dict):
        raise ValueError(f"{path}: not a bench result (a {type(result).__name__}, not an object)")
    check(result, RESULT_KEYS, "")
    check(result["evaluation"], EVALUATION_KEYS, "evaluation.")
    if result["algo"] not in ALGOS:
        raise ValueError(f"{path}: not a bench result (algo {result['algo']!r}: none of {', '.join(ALGOS)})")
    from embedrl.train.scenarios import SCENARIOS

    if result["scenario"] not in SCENARIOS:
        raise ValueError(f"{path}: not a bench result (scenario {result['scenario']!r}: an unknown one)")
    reached_at = (result["episodes_to_criterion"], result["steps_to_criterion"])
    if result["criterion_reached"] and None in reached_at:
        raise ValueError(f"{path}: not a bench result (criterion_reached without its step and episode)")
    for name in ("curve.csv", "config.json"):  # the learning curves are drawn from the run's folder
        if not (Path(result["run"]) / name).is_file():
            raise ValueError(f"{path}: its run folder {result['run']} has no {name}")


def write_table(runs: list[dict[str, Any]], out: Path, note: str, failed: list[str]) -> str:
    """Per algorithm the median over its runs beside the study's numbers, the potential-field controller
    on the same test seeds, and the runs that failed; ``bench.md`` and ``bench.json`` in ``out``."""
    from embedrl.train.potential_field import PotentialFieldController
    from embedrl.train.scenarios import SCENARIOS

    scenarios = {r["scenario"] for r in runs}
    if len(scenarios) != 1:
        raise ValueError(
            f"runs of several scenarios ({', '.join(sorted(scenarios))}): one table per scenario"
        )
    scenario = scenarios.pop()
    algos = [a for a in ALGO_ORDER if any(r["algo"] == a for r in runs)]
    eval_episodes = runs[0]["evaluation"]["episodes"]
    study = STUDY_BY_SCENARIO.get(scenario)  # None: the study never ran this scenario
    pf = evaluate(
        PotentialFieldController(scenario=scenario), eval_episodes, BENCH_TEST_SEED, "potential-field",
        env_id=SCENARIOS[scenario].env_id,
    )  # fmt: skip
    rows = {
        algo: _row(sorted((r for r in runs if r["algo"] == algo), key=lambda r: r["seed"])) for algo in algos
    }
    seeds = sorted({r["seed"] for r in runs})
    pf_line = (
        f"Potential-field controller on the same {eval_episodes} seeds: {pf.successes} / {pf.collisions} / "
        f"{pf.timeouts}, average reward {pf.mean_return:.3f}, reliability {100 * pf.success_rate:.1f}%"
        + (" (it reads only this scenario's observation: without the shelf's velocity it drives as in the "
           "static scenario)." if scenario in TEACHERS else ".")
    )  # fmt: skip
    text = (
        f"Scenario `{scenario}`. Median [95% bootstrap interval, from {MIN_SEEDS_FOR_INTERVAL} seeds] over "
        f"seeds {', '.join(map(str, seeds))}; {note}."
    )
    failures = "".join(f"\n\nFailed: {f}" for f in failed)
    table = _markdown(algos, rows, study, eval_episodes) + "\n\n" + pf_line + "\n\n" + text + failures + "\n"
    out.mkdir(parents=True, exist_ok=True)
    (out / "bench.md").write_text(table)
    plot_learning_curves(runs, algos, out / "learning_curves.png", f"Scenario {scenario}: {note}")
    write_json(
        {
            "algos": algos, "scenario": scenario, "seeds": seeds, "note": note, "rows": rows, "study": study,
            "runs": runs, "failed": failed,
            "potential_field": {
                k: getattr(pf, k)
                for k in ("successes", "collisions", "timeouts", "success_rate", "mean_return")
            },
            "provenance": provenance(),
        },
        out / "bench.json",
    )  # fmt: skip
    return table


def plot_learning_curves(runs: list[dict[str, Any]], algos: list[str], path: Path, title: str) -> None:
    """Per algorithm the 50-episode training average against env steps: median and worst-to-best band
    over seeds, where learning starts (random actions before it), the demonstrations the replay buffer
    held from the start, and the study's criterion."""
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    from embedrl.common import atomic_write
    from embedrl.train import curves
    from embedrl.train.monitor import STOP_THRESHOLD, STOP_WINDOW

    width = max(5.5 * len(algos), 9.0)  # room for the legend and the title with a single panel
    fig, axes = plt.subplots(1, len(algos), figsize=(width, 4.8), sharey=True, squeeze=False)
    for ax, algo in zip(axes[0], algos, strict=True):
        mine = [r for r in runs if r["algo"] == algo]
        end = max(r["total_steps"] for r in mine)
        grid = np.linspace(0, end, curves.GRID_POINTS)
        median, low, high = curves.median_band(
            np.array([curves.on_grid(*curves.load(Path(r["run"]))[:2], grid) for r in mine])
        )
        ax.fill_between(
            grid, low, high, color="tab:blue", alpha=0.2, lw=0, label=f"worst to best of {len(mine)} seed(s)"
        )
        ax.plot(grid, median, color="tab:blue", lw=1.6, label="median over seeds")
        hyper = json.loads((Path(mine[0]["run"]) / "config.json").read_text())["hyperparameters"]
        starts = int(hyper.get("learning_starts", 0))
        if starts:
            ax.axvline(
                starts,
                color="0.4",
                ls=":",
                lw=1.2,
                label=f"learning starts (random actions before, {starts:,} steps)",
            )
        demos = int(hyper.get("demonstrations", hyper.get("warm_start_demonstrations", 0)))
        if demos:
            ax.plot([], [], " ", label=f"{demos} demonstration episodes given before step 0")
        ax.axhline(
            STOP_THRESHOLD, color="k", ls="--", lw=0.8, label=f"the study's criterion ({STOP_THRESHOLD:g})"
        )
        ax.set(title=algo.upper(), xlabel="env steps", xlim=(0, end))
    axes[0][0].set_ylabel(f"return, {STOP_WINDOW}-episode training average")
    handles, labels = axes[0][0].get_legend_handles_labels()  # the same marks in every panel
    fig.legend(handles, labels, loc="lower center", ncols=2 if len(algos) == 1 else 3, fontsize="small")
    fig.suptitle("\n".join(textwrap.wrap(title, width=int(14 * width))), fontsize="small")
    fig.tight_layout(rect=(0, 0.2 if len(algos) == 1 else 0.14, 1, 1))
    try:
        atomic_write(path, lambda tmp: fig.savefig(tmp, dpi=100, bbox_inches="tight", format="png"))
    finally:
        plt.close(fig)


def _row(mine: list[dict[str, Any]]) -> dict[str, str]:
    """One algorithm's column of the table, from its runs' summaries."""
    reached = [r for r in mine if r["criterion_reached"]]
    ev = [r["evaluation"] for r in mine]
    return {
        "reached": f"{len(reached)} / {len(mine)}",
        "episodes": _cell([r["episodes_to_criterion"] + r["demonstration_episodes"] for r in reached], ".0f"),
        "episodes_learning": _cell(
            [r["episodes_to_criterion"] - r["warmup_episodes"] for r in reached], ".0f"
        ),
        "steps": _cell([r["steps_to_criterion"] for r in reached], ".0f"),
        "average_reward": _cell(
            [r["average50_at_stop"] for r in mine if r["average50_at_stop"] is not None], ".3f"
        ),
        "evaluation_return": _cell([e["mean_return"] for e in ev], ".3f"),
        "outcomes": " ; ".join(f"{e['successes']} / {e['collisions']} / {e['timeouts']}" for e in ev),
        "mean_time_s": _cell([e["mean_time_s"] for e in ev if e["mean_time_s"] is not None], ".2f"),
        "reliability": _cell([100 * e["success_rate"] for e in ev], ".1f"),
        "reliability_range": " / ".join(
            f"{q:.1f}" for q in np.percentile([100 * e["success_rate"] for e in ev], [0, 50, 100])
        ),
        "reliability_per_seed": " ; ".join(
            f"{r['seed']}: {100 * r['evaluation']['success_rate']:.1f}" for r in mine
        ),
        "cloning_alone": _cell(
            [
                100 * r["warm_start_evaluation"]["success_rate"]
                for r in mine
                if r.get("warm_start_evaluation")
            ],
            ".1f",
        ),
        "validated": f"{sum(r['validation_target_step'] is not None for r in mine)} / {len(mine)}",
        "validation_steps": _cell(
            [r["validation_target_step"] for r in mine if r["validation_target_step"] is not None], ".0f"
        ),
        "updates": _cell([r["updates"] for r in mine], ".0f"),
        "wall_clock_s": _cell([r["wall_clock_s"] for r in mine], ".0f"),
    }


ROW_LABELS = [
    ("reached", "runs reaching the stop criterion"),
    ("episodes", "episodes to the study's criterion, all (demonstrations and random warm-up included)"),
    ("episodes_learning", "episodes to the study's criterion, learning only (without those)"),
    ("steps", "env steps to the study's criterion"),
    ("average_reward", "average reward at the stop (training, last 50 episodes)"),
    ("evaluation_return", "average reward of the selected policy ({eval_episodes} test runs)"),
    ("outcomes", "successful / collisions / no result"),
    ("mean_time_s", "mean time (s)"),
    ("reliability", "reliability (%)"),
    ("reliability_range", "reliability worst / median / best seed (%)"),
    ("reliability_per_seed", "reliability per seed (%)"),
    ("cloning_alone", "reliability of behaviour cloning alone, before any PPO update (%)"),
    ("validated", "runs reaching the deployable criterion (97% of 100 validation runs)"),
    ("validation_steps", "env steps to the deployable criterion"),
    ("updates", "policy updates by the algorithm (SB3 _n_updates; a warm start does not count)"),
    ("wall_clock_s", "wall-clock time (s)"),
]
"""The table's rows, top to bottom: key in :func:`_row`'s column, label."""


def _markdown(
    algos: list[str],
    rows: dict[str, dict[str, str]],
    study: dict[str, dict[str, Any]] | None,
    eval_episodes: int,
) -> str:
    """Our column beside the study's for each algorithm (ours alone in a scenario the study never ran)."""
    labels = [(key, label.format(eval_episodes=eval_episodes)) for key, label in ROW_LABELS]
    if study is None:
        header = "| | " + " | ".join(a.upper() for a in algos) + " |"
        lines = [header, "|---" * (1 + len(algos)) + "|"]
        lines += [f"| {label} | " + " | ".join(rows[a][key] for a in algos) + " |" for key, label in labels]
        return "\n".join(lines)
    header = "| | " + " | ".join(f"{a.upper()} (ours) | {a.upper()} (study)" for a in algos) + " |"
    lines = [header, "|---" * (1 + 2 * len(algos)) + "|"]
    for key, label in labels:
        cells = []
        for a in algos:
            value = study.get(a, {}).get(key, "-" if a not in study else "")
            cells += [rows[a][key], str(value)]
        lines.append(f"| {label} | " + " | ".join(cells) + " |")
    return "\n".join(lines)
