"""Pictures for people: evaluation trajectories over the warehouse map."""

from __future__ import annotations

from pathlib import Path

import matplotlib

matplotlib.use("Agg")
import matplotlib.pyplot as plt
from matplotlib.patches import Rectangle

from embedrl.common import atomic_write
from embedrl.train import layout
from embedrl.train.evaluate import EvalReport

OUTCOME_COLOURS = {"success": "tab:green", "collision": "tab:red", "timeout": "tab:orange"}


def plot_trajectories(report: EvalReport, path: Path) -> None:
    """Draw every episode's path over the map, coloured by outcome; write a PNG atomically."""
    fig, ax = plt.subplots(figsize=(9, 4.8))
    for rect in layout.OBSTACLES:
        colour = "saddlebrown" if rect in layout.SHELVES else "dimgray"
        ax.add_patch(Rectangle((rect.x0, rect.y0), rect.x1 - rect.x0, rect.y1 - rect.y0, color=colour))
    ax.plot([-layout.GAP_WIDTH / 2, layout.GAP_WIDTH / 2], [layout.GOAL_Y] * 2, color="tab:green", lw=3)
    for r in report.results:
        xs = [p[0] for p in r.trajectory]
        ys = [p[1] for p in r.trajectory]
        colour = OUTCOME_COLOURS[r.outcome]
        ax.plot(xs, ys, "-", color=colour, lw=1, alpha=0.7)
        ax.plot(xs[:1], ys[:1], "o", color=colour, ms=3)
    for outcome, colour in OUTCOME_COLOURS.items():
        ax.plot([], [], color=colour, label=outcome)
    v = layout.VIEW
    ax.set(xlim=(v.x0, v.x1), ylim=(v.y0, v.y1), aspect="equal", xlabel="x [m]", ylabel="y [m]")
    last_seed = report.seed + report.episodes - 1
    ax.set_title(
        f"{report.policy}: {report.successes}/{report.episodes} successes, "
        f"mean return {report.mean_return:.3f} (seeds {report.seed}..{last_seed})"
    )
    ax.legend(loc="upper right", fontsize="small")
    try:
        atomic_write(path, lambda tmp: fig.savefig(tmp, dpi=110, bbox_inches="tight", format="png"))
    finally:
        plt.close(fig)


def plot_progress(curve_csv: Path, path: Path, title: str) -> None:
    """MATLAB-style training progress: episode return, 50-episode average, Episode Q0."""
    import csv

    with curve_csv.open() as f:
        rows = list(csv.DictReader(f))
    episodes = [int(r["episode"]) for r in rows]
    fig, ax = plt.subplots(figsize=(9, 4.5))
    ax.plot(
        episodes,
        [float(r["return"]) for r in rows],
        color="tab:blue",
        lw=0.6,
        alpha=0.5,
        label="episode return",
    )
    ax.plot(episodes, [float(r["average50"]) for r in rows], color="tab:red", lw=1.8, label="average of 50")
    ax.plot(episodes, [float(r["q0"]) for r in rows], color="tab:orange", lw=1.0, ls="--", label="Episode Q0")
    ax.axhline(2.0, color="gray", ls=":", lw=1, label="stop criterion (2)")
    ax.set(xlabel="episode", ylabel="return", title=title)
    ax.legend(loc="lower right", fontsize="small")
    try:
        atomic_write(path, lambda tmp: fig.savefig(tmp, dpi=110, bbox_inches="tight", format="png"))
    finally:
        plt.close(fig)
