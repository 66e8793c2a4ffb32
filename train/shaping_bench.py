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
"""

from __future__ import annotations

from pathlib import Path
from typing import Any

import numpy as np

from embedrl.common import atomic_write, provenance, write_json
from embedrl.train import curves as curves_
from embedrl.train.monitor import STOP_THRESHOLD, STOP_WINDOW
from embedrl.train.scenarios import DEFAULT_SCENARIO
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
) -> str:
    """Train every (algorithm, reward, seed) from scratch on the static scenario (on Ray with ``ray``); the
    table, also written with the runs (JSON) and the curves (PNG)."""
    seed_list = list(range(seed_offset, seed_offset + seeds))
    runs = _train_all(algos, seed_list, preset, out, max_steps, eval_episodes, workers, gain, overrides, ray)
    note = (
        f"From scratch (preset `{preset}` without demonstrations or a cloned start), static scenario, seeds "
        f"{seed_list[0]}..{seed_list[-1]}, at most {max_steps} env steps, shaping gain {gain} per metre. "
        "Both columns count only the eq. 19 return (the shaping term is left out of the criterion)."
    )
    table = _markdown(runs, algos, eval_episodes) + "\n\n" + note + "\n"
    out.mkdir(parents=True, exist_ok=True)
    (out / "shaping.md").write_text(table)
    write_json(
        {
            "algos": algos,
            "seeds": seed_list,
            "preset": preset,
            "max_steps": max_steps,
            "shaping_gain": gain,
            "overrides": list(overrides),
            "runs": runs,
            "provenance": provenance(),
        },
        out / "shaping.json",
    )
    plot(runs, algos, max_steps, out / "shaping.png", f"Learning from scratch, shaping gain {gain}/m")
    return table


def _train_all(
    algos: list[str],
    seed_list: list[int],
    preset: str,
    out: Path,
    max_steps: int,
    eval_episodes: int,
    workers: int,
    gain: float,
    overrides: tuple[str, ...],
    ray: str | None = None,
) -> list[dict[str, Any]]:
    """Every (algorithm, reward, seed) trained (or resumed); each run's summary with its reward variant and
    the mean length of its last 50 episodes."""
    jobs: list[Job] = []
    for algo in algos:
        for reward in REWARD_VARIANTS:
            changes = (*FROM_SCRATCH[algo], f"reward={reward}", *overrides)
            if reward == "shaped":
                changes += (f"shaping_gain={gain}",)
            for seed in seed_list:
                run = out / "runs" / f"{algo}-{reward}-seed{seed}"
                jobs.append(
                    (
                        algo,
                        preset,
                        seed,
                        str(run),
                        max_steps,
                        eval_episodes,
                        DEFAULT_SCENARIO,
                        changes,
                        "study",
                    )
                )
    results, _ = run_all(one_run, jobs, workers, ray, label=lambda job: f"{job[0]} {job[7]} seed {job[2]}")
    runs = []
    for job, result in zip(jobs, results, strict=True):
        if result is None:
            continue  # reported as it failed; the table holds the runs that finished
        _, _, length = curves_.load(Path(job[3]))
        reward = "shaped" if "reward=shaped" in job[7] else "thesis"
        runs.append(
            {
                **result,
                "run": job[3],
                "reward_variant": reward,
                "mean_length_last50": float(np.mean(length[-STOP_WINDOW:])) if len(length) else None,
            }
        )
    return runs


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
