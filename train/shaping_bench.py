"""``embedrl shaping``: does potential-based reward shaping let agents learn from scratch?

Every algorithm is trained from scratch (the preset without demonstrations and without a behaviour-cloned
start) on the same seeds twice: with the study's reward (eq. 19) and with eq. 19 plus potential-based
shaping (``reward="shaped"``, :mod:`train.rewards`). Both are measured the same way: the study's
criterion (the 50-episode training average of the eq. 19 return >= 2; the shaping term is not counted),
env steps to it, and the selected model's success on the bench's test seeds. Runs stop at the criterion or
at the budget. Like the bench, finished runs are reused and interrupted ones resumed.

Writes ``shaping.md`` (the table), ``shaping.json`` (every run) and ``shaping.png`` (the curves: per
algorithm the median over seeds of the 50-episode average and the band between the worst and the best
seed, for each reward).

On the walker (``scenario="walker"``) the rewards compared are the deck's four shaping stages
(:data:`train.deck_reward.VARIANTS`), every run trained to the same budget. Each stage's return is a different
sum, so none is the yardstick: every run is measured by what the stages share, on the deck's whole reward's
env and the same test seeds: episodes without a fall, the success rule (up for the whole 8 s and at least
1 m forward), distance and mean forward speed; the curves are the 50-episode training averages of the
distance walked and of the time upright (from ``episode_sums.csv`` and ``curve.csv``).
"""

from __future__ import annotations

import json
from pathlib import Path
from typing import Any

import numpy as np

from embedrl.common import BENCH_TEST_SEED, atomic_write, provenance, write_json
from embedrl.train import curves as curves_
from embedrl.train.deck_reward import VARIANTS as WALKER_VARIANTS
from embedrl.train.errors import UsageError
from embedrl.train.monitor import STOP_THRESHOLD, STOP_WINDOW
from embedrl.train.scenarios import DEFAULT_SCENARIO, WALKER
from embedrl.train.study_benchmark import Job, one_run
from embedrl.train.sweep import run_all

REWARD_VARIANTS = ("thesis", "shaped")
"""The two rewards compared: the study's, and the study's plus the shaping term."""
FROM_SCRATCH = {
    "ddpg": ("demonstrations=0",),
    "td3": ("demonstrations=0",),
    "sac": ("demonstrations=0",),
    "ppo": ("warm_start_demonstrations=0",),
    "recurrent-ppo": ("warm_start_demonstrations=0",),
}
"""What turns a preset into learning from scratch: no controller demonstrations, no cloned start."""
WALKER_VALIDATION = (10_000, 20)
"""The walker runs' validation: every 10,000 env steps, 20 episodes (its episodes last up to 1,000 steps)."""


def variants(scenario: str) -> tuple[str, ...]:
    """The rewards compared on a scenario: the deck's four stages on the walker, else the study's reward
    with and without potential-based shaping."""
    return tuple(WALKER_VARIANTS) if scenario == WALKER.name else REWARD_VARIANTS


def _range_cell(values: list[float], fmt: str) -> str:
    if not values:
        return "-"
    lo, mid, hi = np.percentile(values, [0, 50, 100])
    return f"{mid:{fmt}} [{lo:{fmt}}, {hi:{fmt}}]" if len(values) > 1 else f"{mid:{fmt}}"


def plot(runs: list[dict[str, Any]], algos: list[str], max_steps: int, path: Path, title: str) -> None:
    """Per algorithm: median and worst-to-best band over seeds of the 50-episode training average, for
    the study's reward and the shaped one; the criterion as a dashed line."""
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt
    from matplotlib.ticker import FuncFormatter

    grid = np.linspace(0, max_steps, curves_.GRID_POINTS)
    columns = min(2, len(algos))
    rows = -(-len(algos) // columns)
    fig, grid_axes = plt.subplots(
        rows, columns, figsize=(6 * columns, 3.6 * rows + 0.8), sharey=True, squeeze=False
    )
    axes = list(grid_axes.flat)
    for ax in axes[len(algos) :]:
        ax.set_visible(False)
    colours = {"thesis": "tab:red", "shaped": "tab:blue"}
    names = {"thesis": "study's reward (eq. 19)", "shaped": "eq. 19 + potential-based shaping"}
    thousands = FuncFormatter(lambda x, _: f"{x / 1000:.0f}k" if x else "0")
    for ax, algo in zip(axes, algos, strict=False):
        for reward in REWARD_VARIANTS:
            mine = [r for r in runs if r["algo"] == algo and r["reward_variant"] == reward]
            if not mine:
                continue
            curves = np.array([curves_.on_grid(*curves_.load(Path(r["run"]))[:2], grid) for r in mine])
            median, lo, hi = curves_.median_band(curves)
            reached = sum(r["criterion_reached"] for r in mine)
            label = f"{names[reward]}: {reached}/{len(mine)} reach it"
            ax.plot(grid, median, color=colours[reward], lw=1.6, label=label)
            ax.fill_between(grid, lo, hi, color=colours[reward], alpha=0.2, lw=0)
        ax.axhline(STOP_THRESHOLD, color="k", ls="--", lw=0.8)
        ax.set(title=algo.upper(), xlabel="env steps", xlim=(0, max_steps))
        ax.xaxis.set_major_formatter(thousands)
        ax.legend(loc="lower right", fontsize="small")
    for row in grid_axes:
        row[0].set_ylabel(f"eq. 19 return,\n{STOP_WINDOW}-episode training average")
    fig.suptitle(f"{title}\nline: median over seeds; band: worst to best seed\ndashed: the study's criterion")
    fig.tight_layout()
    try:
        atomic_write(path, lambda tmp: fig.savefig(tmp, dpi=100, format="png"))
    finally:
        plt.close(fig)


def run_shaping(
    algos: list[str],
    seeds: int,
    seed_offset: int,
    preset: str,
    out: Path,
    max_steps: int,
    eval_episodes: int,
    workers: int,
    gain: float,
    overrides: tuple[str, ...] = (),
    ray: str | None = None,
    scenario: str = DEFAULT_SCENARIO,
    finished_only: bool = False,
) -> str:
    """Train every (algorithm, reward, seed) from scratch on ``scenario`` (on Ray with ``ray``); the table,
    also written with the runs (JSON) and the curves (PNG). ``finished_only``: train nothing, the table of
    the runs that finished this budget (their ``result.json``), the others named as not finished."""
    seed_list = list(range(seed_offset, seed_offset + seeds))
    jobs = _jobs(algos, seed_list, preset, out, max_steps, eval_episodes, gain, overrides, scenario)
    runs = _finished(jobs) if finished_only else _train_all(jobs, workers, ray)
    if finished_only and not runs:
        raise UsageError(
            f"no run under {out / 'runs'} has finished {max_steps} env steps: nothing to tabulate"
        )
    missing = [Path(job[3]).name for job in jobs if job[3] not in {r["run"] for r in runs}]
    walker = scenario == WALKER.name
    if walker:
        note = (
            f"Walker, preset `{preset}`{''.join(f' --set {o}' for o in overrides)}, the deck's four reward "
            f"stages, seeds {seed_list[0]}..{seed_list[-1]}, {max_steps} env steps each; every model tested "
            f"on the deck's whole reward's env, {eval_episodes} episodes from seed {BENCH_TEST_SEED} (seeds "
            "no run trained or validated on). Success: up for the whole 8 s and at least 1 m forward."
        )
        table = _walker_markdown(runs, algos, eval_episodes)
    else:
        note = (
            f"From scratch (preset `{preset}` without demonstrations or a cloned start), static scenario, "
            f"seeds {seed_list[0]}..{seed_list[-1]}, at most {max_steps} env steps, shaping gain {gain} "
            "per metre. Both columns count only the eq. 19 return (the shaping term is left out of the "
            "criterion)."
        )
        table = _markdown(runs, algos, eval_episodes)
    if missing:
        note += f" Not finished at this budget ({len(missing)} of {len(jobs)} runs): {', '.join(missing)}."
    table += "\n\n" + note + "\n"
    out.mkdir(parents=True, exist_ok=True)
    (out / "shaping.md").write_text(table)
    write_json(
        {
            "scenario": scenario,
            "algos": algos,
            "rewards": list(variants(scenario)),
            "seeds": seed_list,
            "preset": preset,
            "max_steps": max_steps,
            "shaping_gain": None if walker else gain,
            "overrides": list(overrides),
            "runs": runs,
            "provenance": provenance(),
        },
        out / "shaping.json",
    )
    if walker:
        plot_walker(
            runs, algos, max_steps, out / "shaping.png", f"The deck's reward stages, {max_steps} steps"
        )
    else:
        plot(runs, algos, max_steps, out / "shaping.png", f"Learning from scratch, shaping gain {gain}/m")
    return table


def _jobs(
    algos: list[str],
    seed_list: list[int],
    preset: str,
    out: Path,
    max_steps: int,
    eval_episodes: int,
    gain: float,
    overrides: tuple[str, ...],
    scenario: str,
) -> list[Job]:
    """One job per (algorithm, reward, seed). The static scenario's runs stop at the study's criterion;
    the walker's train to the budget, validated as :data:`WALKER_VALIDATION` says."""
    walker = scenario == WALKER.name
    jobs: list[Job] = []
    for seed in seed_list:  # seed by seed: a sitting cut short leaves whole seeds of every reward
        for algo in algos:
            for reward in variants(scenario):
                changes = (*FROM_SCRATCH[algo], f"reward={reward}", *overrides)
                if reward == "shaped":
                    changes += (f"shaping_gain={gain}",)
                run = str(out / "runs" / f"{algo}-{reward}-seed{seed}")
                stop, validation = ("budget", WALKER_VALIDATION) if walker else ("study", None)
                jobs.append(
                    (algo, preset, seed, run, max_steps, eval_episodes, scenario, changes, stop, validation)
                )
    return jobs


def _finished(jobs: list[Job]) -> list[dict[str, Any]]:
    """The runs of ``jobs`` that finished their budget (their ``result.json`` says so), their models
    evaluated again on the test seeds (nothing trained), with what :func:`_train_all` adds."""
    from embedrl.train.study_benchmark import RESULT_FILE

    runs = []
    for job in jobs:
        path = Path(job[3]) / RESULT_FILE
        if path.is_file() and json.loads(path.read_text()).get("max_steps") == job[4]:
            runs.append(_with_training_tail(job, one_run(job)))  # a finished run: evaluated, not trained
    return runs


def _reward_of(changes: tuple[str, ...]) -> str:
    """The reward variant a job's overrides set."""
    return next(c.split("=", 1)[1] for c in changes if c.startswith("reward="))


def _train_all(jobs: list[Job], workers: int, ray: str | None = None) -> list[dict[str, Any]]:
    """Every job trained (or resumed); each run's summary with its reward variant, the mean length of its
    last 50 episodes and, where it logged them, its last 50 episodes' mean distance."""
    results, _ = run_all(one_run, jobs, workers, ray, label=lambda job: f"{job[0]} {job[7]} seed {job[2]}")
    # a run that failed is reported as it failed; the table holds the runs that finished
    return [_with_training_tail(j, r) for j, r in zip(jobs, results, strict=True) if r is not None]


def _with_training_tail(job: Job, result: dict[str, Any]) -> dict[str, Any]:
    """A run's result with its reward variant, the mean length of its last 50 training episodes and,
    where it logged them, their mean distance."""
    _, _, length = curves_.load(Path(job[3]))
    distance = _distances(Path(job[3]))[1]
    return {
        **result,
        "run": job[3],
        "reward_variant": _reward_of(job[7]),
        "mean_length_last50": float(np.mean(length[-STOP_WINDOW:])) if len(length) else None,
        "mean_distance_last50": float(np.mean(distance[-STOP_WINDOW:])) if len(distance) else None,
    }


def _distances(run: Path) -> tuple[np.ndarray, np.ndarray]:
    """(env steps, distance walked) per training episode from the run's ``episode_sums.csv`` (empty arrays
    for a run without one)."""
    import csv

    from embedrl.train.monitor import EPISODE_SUMS_FILE

    path = run / EPISODE_SUMS_FILE
    if not path.is_file():
        return np.zeros(0), np.zeros(0)
    with path.open() as f:
        rows = list(csv.DictReader(f))
    return (
        np.array([int(r["steps"]) for r in rows], dtype=float),
        np.array([float(r["distance"]) for r in rows]),
    )


def _markdown(runs: list[dict[str, Any]], algos: list[str], eval_episodes: int) -> str:
    """One column per (algorithm, reward variant)."""
    columns = [(a, r) for a in algos for r in REWARD_VARIANTS]
    rows: list[tuple[str, list[str]]] = []

    def row(label: str, cell: Any) -> None:
        cells = []
        for algo, reward in columns:
            mine = [r for r in runs if r["algo"] == algo and r["reward_variant"] == reward]
            cells.append(cell(mine))
        rows.append((label, cells))

    row(
        "runs reaching the study's criterion",
        lambda m: f"{sum(r['criterion_reached'] for r in m)} / {len(m)}",
    )
    row(
        "env steps to the criterion (median [fastest, slowest] of those reaching it)",
        lambda m: _range_cell([r["steps_to_criterion"] for r in m if r["criterion_reached"]], ".0f"),
    )
    row(
        "training episodes to the criterion",
        lambda m: _range_cell([r["episodes_to_criterion"] for r in m if r["criterion_reached"]], ".0f"),
    )
    row(
        "eq. 19 average of the last 50 training episodes at the stop (median [worst, best])",
        lambda m: _range_cell(
            [r["average50_at_stop"] for r in m if r["average50_at_stop"] is not None], ".2f"
        ),
    )
    row(
        "mean length of the last 50 training episodes (steps; about 18 through the gap, 2-3 a crash at once)",
        lambda m: _range_cell(
            [r["mean_length_last50"] for r in m if r["mean_length_last50"] is not None], ".1f"
        ),
    )
    row(
        f"success of the selected model on {eval_episodes} test episodes, % (median [worst, best])",
        lambda m: _range_cell([100 * r["evaluation"]["success_rate"] for r in m], ".1f"),
    )
    row("env steps trained (median)", lambda m: _range_cell([r["total_steps"] for r in m], ".0f"))
    row("wall-clock time, s (median)", lambda m: _range_cell([r["wall_clock_s"] for r in m], ".0f"))
    header = "| | " + " | ".join(f"{a.upper()} {'shaped' if r == 'shaped' else 'eq. 19'}" for a, r in columns)
    lines = [header + " |", "|---" * (1 + len(columns)) + "|"]
    lines += [f"| {label} | " + " | ".join(cells) + " |" for label, cells in rows]
    return "\n".join(lines)


def _walker_markdown(runs: list[dict[str, Any]], algos: list[str], eval_episodes: int) -> str:
    """The walker's table: one column per (algorithm, deck stage); each cell the median over seeds with
    the worst and the best seed."""
    columns = [(a, r) for a in algos for r in WALKER_VARIANTS]

    def cells(value: Any, fmt: str) -> list[str]:
        out = []
        for algo, reward in columns:
            mine = [r for r in runs if r["algo"] == algo and r["reward_variant"] == reward]
            out.append(_range_cell([v for v in map(value, mine) if v is not None], fmt))
        return out

    def share(key: str) -> Any:
        return lambda r: 100 * r["evaluation"][key] / r["evaluation"]["episodes"]

    def test(key: str) -> Any:
        return lambda r: r["evaluation"].get(key)

    def train(key: str) -> Any:
        return lambda r: r.get(key)

    def upright(r: dict[str, Any]) -> float:
        return 100 - float(share("collisions")(r))

    up_s = WALKER.sample_time_s
    rows = [
        (f"test episodes without a fall, % ({eval_episodes} a run)", cells(upright, ".0f")),
        ("test episodes succeeding, % (8 s up, >= 1 m)", cells(share("successes"), ".0f")),
        ("test distance, mean per run [m]", cells(test("mean_distance_m"), ".2f")),
        ("test forward speed, mean per run [m/s]", cells(test("mean_speed_m_s"), ".2f")),
        ("test time up, mean per run [s]", cells(lambda r: r["evaluation"]["mean_steps"] * up_s, ".2f")),
        ("test return on the deck's whole reward, mean per run", cells(test("mean_return"), ".1f")),
        ("training: distance, last 50 episodes [m]", cells(train("mean_distance_last50"), ".2f")),
        ("training: episode length, last 50 episodes [steps]", cells(train("mean_length_last50"), ".0f")),
        ("env steps trained", cells(train("total_steps"), ".0f")),
        ("wall-clock time of training, s", cells(train("wall_clock_s"), ".0f")),
    ]  # fmt: skip
    header = "| median [worst, best] over seeds | " + " | ".join(f"{a.upper()} `{r}`" for a, r in columns)
    lines = [header + " |", "|---" * (1 + len(columns)) + "|"]
    lines += [f"| {label} | " + " | ".join(row) + " |" for label, row in rows]
    return "\n".join(lines)


WALKER_COLOURS = {"velocity": "tab:red", "upright": "tab:orange", "effort": "tab:green", "deck": "tab:blue"}
"""One colour per deck stage in the walker's curves."""


def plot_walker(runs: list[dict[str, Any]], algos: list[str], max_steps: int, path: Path, title: str) -> None:
    """Per algorithm, two panels: the 50-episode training average of the distance walked and of the time
    upright, median over seeds and worst-to-best band, one colour per deck stage."""
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt
    from matplotlib.ticker import FuncFormatter

    grid = np.linspace(0, max_steps, curves_.GRID_POINTS)
    fig, grid_axes = plt.subplots(len(algos), 2, figsize=(12, 3.8 * len(algos) + 0.8), squeeze=False)
    thousands = FuncFormatter(lambda x, _: f"{x / 1000:.0f}k" if x else "0")
    for (distance_ax, time_ax), algo in zip(grid_axes, algos, strict=True):
        for reward in WALKER_VARIANTS:
            mine = [r for r in runs if r["algo"] == algo and r["reward_variant"] == reward]
            if not mine:
                continue
            panels = ((distance_ax, [_distances(Path(r["run"])) for r in mine]),
                      (time_ax, [_lengths(Path(r["run"])) for r in mine]))  # fmt: skip
            for ax, series in panels:
                curves = np.array([curves_.on_grid(s, _average(v), grid) for s, v in series])
                median, lo, hi = curves_.median_band(curves)
                ax.plot(
                    grid,
                    median,
                    color=WALKER_COLOURS[reward],
                    lw=1.6,
                    label=f"{reward} ({len(mine)} seed{'s' if len(mine) > 1 else ''})",
                )
                ax.fill_between(grid, lo, hi, color=WALKER_COLOURS[reward], alpha=0.15, lw=0)
        distance_ax.set(title=f"{algo.upper()}: distance walked", ylabel=f"m, {STOP_WINDOW}-episode average")
        time_ax.set(title=f"{algo.upper()}: time up before the fall (8 s: no fall)",
                    ylabel=f"s, {STOP_WINDOW}-episode average")  # fmt: skip
        starts = sorted({_learning_starts(Path(r["run"])) for r in runs if r["algo"] == algo})
        for ax in (distance_ax, time_ax):
            if len(starts) == 1 and starts[0] > 0:  # the runs' random actions end here
                ax.axvline(starts[0], color="grey", ls=":", lw=1, label="learning starts")
            ax.set(xlabel="env steps", xlim=(0, max_steps))
            ax.xaxis.set_major_formatter(thousands)
            ax.legend(loc="upper left", fontsize="small")
    fig.suptitle(f"{title}\nline: median over seeds; band: worst to best seed")
    fig.tight_layout()
    try:
        atomic_write(path, lambda tmp: fig.savefig(tmp, dpi=100, format="png"))
    finally:
        plt.close(fig)


def _learning_starts(run: Path) -> int:
    """The random-action steps a run took before learning (its ``learning_starts``; 0 without)."""
    return int(json.loads((run / "config.json").read_text())["hyperparameters"].get("learning_starts", 0))


def _lengths(run: Path) -> tuple[np.ndarray, np.ndarray]:
    """(env steps, seconds upright) per training episode of a walker run."""
    steps, _, length = curves_.load(run)
    return steps, length * WALKER.sample_time_s


def _average(values: np.ndarray) -> np.ndarray:
    """The running average over the last ``STOP_WINDOW`` episodes (fewer at the start)."""
    sums = np.cumsum(np.concatenate([[0.0], values]))
    ends = np.arange(1, len(values) + 1)
    starts = np.maximum(ends - STOP_WINDOW, 0)
    return np.asarray((sums[ends] - sums[starts]) / (ends - starts), dtype=float)
