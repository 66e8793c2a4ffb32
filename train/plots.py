"""Pictures for people: evaluation trajectories over the warehouse map."""

from __future__ import annotations

from collections.abc import Sequence
from pathlib import Path

import matplotlib

matplotlib.use("Agg")
import matplotlib.pyplot as plt
from matplotlib.figure import Figure
from matplotlib.patches import Rectangle

from embedrl.common import atomic_write
from embedrl.train import layout
from embedrl.train.evaluate import EvalReport

OUTCOME_COLOURS = {"success": "tab:green", "collision": "tab:red", "timeout": "tab:orange"}
NODE_STYLES = (("-", "o"), ("--", "s"), (":", "^"), ("-.", "D"))
"""Line and start marker of each node's robot on a map of several nodes (colour stays the outcome's)."""


def plot_trajectories(
    report: EvalReport, path: Path, overlay: EvalReport | None = None, nodes: Sequence[int] | None = None
) -> None:
    """Draw every episode's path over the map, coloured by outcome; write a PNG atomically.

    The moving-shelf scenario draws the fixed map and the band the moving shelf sweeps; two robots draw
    the second robot's path dashed. ``overlay`` (the simulation on the same seeds, beside a HIL run) is
    drawn first, thick and grey, so that the run's paths show on top of it wherever they agree. ``nodes``
    (a HIL run of several nodes: the node of each result) gives each node's paths their own line style
    and start marker (:data:`NODE_STYLES`)."""
    fig = trajectory_figure(report, overlay, nodes)
    try:
        atomic_write(path, lambda tmp: fig.savefig(tmp, dpi=110, bbox_inches="tight", format="png"))
    finally:
        plt.close(fig)


def trajectory_figure(
    report: EvalReport, overlay: EvalReport | None = None, nodes: Sequence[int] | None = None
) -> Figure:
    """The figure :func:`plot_trajectories` writes."""
    from embedrl.train.scenarios import has_moving_shelf

    fig, ax = plt.subplots(figsize=(9, 4.8))
    moving = has_moving_shelf(report.env_id)
    for rect in layout.FIXED_OBSTACLES if moving else layout.OBSTACLES:
        colour = "saddlebrown" if rect in layout.SHELVES else "dimgray"
        ax.add_patch(Rectangle((rect.x0, rect.y0), rect.x1 - rect.x0, rect.y1 - rect.y0, color=colour))
    if moving:
        band = (layout.MOVING_SHELF_Y_MIN, layout.MOVING_SHELF_Y_MAX + layout.UPPER_SHELF_DEPTH)
        ax.axhspan(*band, color="saddlebrown", alpha=0.12, label="moving shelf's band")
    ax.plot([-layout.GAP_WIDTH / 2, layout.GAP_WIDTH / 2], [layout.GOAL_Y] * 2, color="tab:green", lw=3,
            label="goal line (cross it)")  # fmt: skip
    for r in overlay.results if overlay else []:
        ax.plot([p[0] for p in r.trajectory], [p[1] for p in r.trajectory], "-", color="0.75", lw=4, zorder=1)
    if overlay:
        ax.plot([], [], "-", color="0.75", lw=4, label=f"{overlay.policy}, same seeds")
    several = nodes is not None and len(set(nodes)) > 1
    for i, r in enumerate(report.results):
        xs = [p[0] for p in r.trajectory]
        ys = [p[1] for p in r.trajectory]
        colour = OUTCOME_COLOURS[r.outcome]
        line, marker = NODE_STYLES[nodes[i] % len(NODE_STYLES)] if several and nodes else ("-", "o")
        ax.plot(xs, ys, line, color=colour, lw=1, alpha=0.9, zorder=2)
        ax.plot(xs[:1], ys[:1], marker, color=colour, ms=3)
        for other in r.other_trajectories:
            ax.plot([p[0] for p in other], [p[1] for p in other], "--", color=colour, lw=1, alpha=0.7)
            ax.plot([p[0] for p in other][:1], [p[1] for p in other][:1], "s", color=colour, ms=3)
    for outcome, colour in OUTCOME_COLOURS.items():
        ax.plot([], [], color=colour, label=outcome)
    if several and nodes:
        for k in sorted(set(nodes)):
            line, marker = NODE_STYLES[k % len(NODE_STYLES)]
            ax.plot([], [], marker + line, color="k", ms=3, lw=1, label=f"node {k}: start, path")
    else:
        ax.plot([], [], "o", color="k", ms=3, label="start")
    if any(r.other_trajectories for r in report.results):
        ax.plot([], [], "s--", color="k", ms=3, lw=1, label="second robot: start, path")
    v = layout.VIEW
    ax.set(xlim=(v.x0, v.x1), ylim=(v.y0, v.y1), aspect="equal", xlabel="x [m]", ylabel="y [m]")
    ax.set_title(
        f"{report.policy}: {report.successes}/{report.episodes} successes, "
        f"mean return {report.mean_return:.3f} ({_seeds(report)})"
    )
    ax.legend(loc="upper left", bbox_to_anchor=(1.01, 1.0), fontsize="small")  # beside: hides no path
    return fig


def _seeds(report: EvalReport) -> str:
    """The episodes' seeds: a range when they are one (several HIL nodes each have their own)."""
    seeds = sorted({r.seed for r in report.results})
    if not seeds or seeds == list(range(seeds[0], seeds[-1] + 1)):
        return f"seeds {report.seed}..{report.seed + report.episodes - 1}"
    shown = ", ".join(str(s) for s in seeds[:6])
    return f"seeds {shown}{', ...' if len(seeds) > 6 else ''}"


def plot_progress(curve_csv: Path, path: Path, title: str, warmup_steps: int = 0) -> None:
    """Training progress as MATLAB draws it: each episode's return, the 50-episode average and the critic's
    value of the start state (Q0), with the random warm-up (``warmup_steps`` env steps before any learning)
    shaded, so that its flat start does not read as learning that is stuck."""
    import csv

    with curve_csv.open() as f:
        rows = list(csv.DictReader(f))
    episodes = [int(r["episode"]) for r in rows]
    fig, ax = plt.subplots(figsize=(9, 4.5))
    warm = [int(r["episode"]) for r in rows if int(r["steps"]) <= warmup_steps]
    if warm:
        ax.axvspan(0, max(warm), color="0.9",
                   label=f"random warm-up: {warmup_steps:,} steps before learning starts")  # fmt: skip
    ax.plot(episodes, [float(r["return"]) for r in rows], color="tab:blue", lw=0.6, alpha=0.5,
            label="episode return")  # fmt: skip
    ax.plot(episodes, [float(r["average50"]) for r in rows], color="tab:red", lw=1.8, label="average of 50")
    ax.plot(episodes, [float(r["q0"]) for r in rows], color="tab:orange", lw=1.0, ls="--",
            label="critic's value of the start state (Q0)")  # fmt: skip
    ax.axhline(2.0, color="gray", ls=":", lw=1, label="stop criterion (2)")
    ax.set(xlabel="training episode", ylabel="return", title=title)
    ax.legend(loc="lower right", fontsize="small")
    try:
        atomic_write(path, lambda tmp: fig.savefig(tmp, dpi=110, bbox_inches="tight", format="png"))
    finally:
        plt.close(fig)


SUCCESS_WINDOW = 100
"""Training episodes per point of the success plot (per robot)."""


def plot_successes(curve_csv: Path, evaluations_csv: Path | None, path: Path, title: str) -> None:
    """Successes over training, per robot (the study's two-robot figures): the share of each robot's last
    100 training episodes that got through, and the validation evaluations' success rate."""
    import csv

    import numpy as np

    with curve_csv.open() as f:
        rows = list(csv.DictReader(f))
    fig, ax = plt.subplots(figsize=(9, 4.5))
    robots = sorted({int(r["robot"]) for r in rows})
    for robot in robots:
        mine = [r for r in rows if int(r["robot"]) == robot]
        if len(mine) < SUCCESS_WINDOW:
            continue
        success = np.array([float(r["success"]) for r in mine])
        rate = np.convolve(success, np.ones(SUCCESS_WINDOW) / SUCCESS_WINDOW, mode="valid")
        steps = [int(r["steps"]) for r in mine][SUCCESS_WINDOW - 1 :]
        who = f"robot {robot + 1}: " if len(robots) > 1 else ""
        ax.plot(steps, 100 * rate, lw=1.2, label=f"{who}share of the last {SUCCESS_WINDOW} training episodes")
    if evaluations_csv is not None and evaluations_csv.is_file():
        with evaluations_csv.open() as f:
            evals = list(csv.DictReader(f))
        ax.plot(
            [int(r["steps"]) for r in evals],
            [100 * float(r["success_rate"]) for r in evals],
            "k.-",
            lw=1,
            label="validation (deterministic, every robot through)",
        )
    ax.set(xlabel="env steps (all robots)", ylabel="successes [%]", ylim=(-2, 102), title=title)
    if ax.get_legend_handles_labels()[0]:
        ax.legend(loc="lower right", fontsize="small")
    else:
        ax.text(0.5, 0.5, f"fewer than {SUCCESS_WINDOW} episodes per robot, no evaluation yet",
                ha="center", transform=ax.transAxes)  # fmt: skip
    try:
        atomic_write(path, lambda tmp: fig.savefig(tmp, dpi=110, bbox_inches="tight", format="png"))
    finally:
        plt.close(fig)


REWARD_FIELD_GRID = 0.01
"""Grid spacing of the reward-field plot [m]."""
EXAMPLE_SHELF = (0.4, 0.6, 0.2)
"""Where the reward-field plot of the moving-shelf scenario shows the shelf: centre x, lower edge, vx."""
EXAMPLE_OTHER_ROBOT = (-0.9, 0.3, 0.0)
"""Where the reward-field plot of the two-robot scenario shows the other robot: x, y, theta."""


def plot_reward_field(scenario: str, path: Path) -> None:
    """The potential-field reward's position term over the map (:func:`train.rewards.field`): the study's
    attraction towards the gap minus the contours of every obstacle; for the moving shelf at one example
    position (it moves with the shelf), for two robots around one example position of the other robot."""
    import numpy as np

    from embedrl.train import rewards
    from embedrl.train.robot import ROBOT_LENGTH, ROBOT_WIDTH
    from embedrl.train.scenarios import OTHER_ROBOT_FIELDS, SCENARIOS, field_indices, has_moving_shelf

    moving = has_moving_shelf(SCENARIOS[scenario].env_id)
    obstacles: tuple[layout.Rect, ...] = layout.OBSTACLES
    others: list[tuple[float, float, float]] = []
    note = "static map"
    if moving:
        cx, y0, vx = EXAMPLE_SHELF
        obstacles = (*layout.FIXED_OBSTACLES, layout.moving_shelf(cx, y0))
        note = f"moving shelf at x = {cx} m, moving at {vx} m/s (the contours move with it)"
    elif field_indices(SCENARIOS[scenario], OTHER_ROBOT_FIELDS) is not None:
        others = [EXAMPLE_OTHER_ROBOT]
        note = f"other robot at ({EXAMPLE_OTHER_ROBOT[0]}, {EXAMPLE_OTHER_ROBOT[1]}) m"
    v = layout.VIEW
    xs = np.arange(v.x0, v.x1 + 1e-9, REWARD_FIELD_GRID)
    ys = np.arange(v.y0, v.y1 + 1e-9, REWARD_FIELD_GRID)
    values = np.array([[rewards.field(float(x), float(y), obstacles, others) for x in xs] for y in ys])
    # The colour scale spans the arena (below the goal line the attraction keeps growing).
    inside = values[ys >= layout.GOAL_Y]
    fig, ax = plt.subplots(figsize=(10, 5.2))
    mesh = ax.pcolormesh(
        xs, ys, values, cmap="viridis", shading="auto", vmin=float(inside.min()), vmax=float(inside.max())
    )
    fig.colorbar(mesh, ax=ax, label="reward at a point (before the per-step costs) [-]")
    ax.contour(xs, ys, values, levels=12, colors="white", linewidths=0.4, alpha=0.6)
    for rect in obstacles:
        ax.add_patch(
            Rectangle((rect.x0, rect.y0), rect.x1 - rect.x0, rect.y1 - rect.y0, fill=False, ec="white", lw=1)
        )
    if moving:
        cx, y0, vx = EXAMPLE_SHELF
        ax.annotate(
            "",
            xy=(cx + 0.6, y0 + 0.15),
            xytext=(cx, y0 + 0.15),
            arrowprops={"arrowstyle": "->", "color": "white", "lw": 2},
        )
    for x, y, _ in others:
        ax.add_patch(
            Rectangle(
                (x - ROBOT_LENGTH / 2, y - ROBOT_WIDTH / 2), ROBOT_LENGTH, ROBOT_WIDTH, fill=False, ec="red"
            )
        )
    ax.plot([-layout.GAP_WIDTH / 2, layout.GAP_WIDTH / 2], [layout.GOAL_Y] * 2, color="tab:green", lw=3,
            label="goal line (cross it)")  # fmt: skip
    ax.set(xlim=(v.x0, v.x1), ylim=(v.y0, v.y1), aspect="equal", xlabel="x [m]", ylabel="y [m]")
    ax.set_title(
        f"Potential-field reward, {scenario} ({note})\n"
        "0.06 e^(-3y) + 0.05 e^(-8x^2) - 0.05 sum_obstacles e^(-d / 0.05 m); a step averages it over the "
        "robot's 4 corners",
        fontsize="small",
    )
    try:
        atomic_write(path, lambda tmp: fig.savefig(tmp, dpi=110, bbox_inches="tight", format="png"))
    finally:
        plt.close(fig)
