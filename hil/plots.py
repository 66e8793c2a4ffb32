"""HIL pictures: the round-trip latency histogram (trajectories come from train.plots)."""

from __future__ import annotations

from pathlib import Path

import matplotlib

matplotlib.use("Agg")
import matplotlib.pyplot as plt

from embedrl.common import atomic_write


def plot_latency(latencies_us: list[float], path: Path, sandbox: str, realtime: bool) -> None:
    fig, ax = plt.subplots(figsize=(7, 4))
    if latencies_us:
        ax.hist([v / 1000 for v in latencies_us], bins=50, color="tab:blue")
    ax.set(
        xlabel="round trip: observation frames out -> action frame in [ms]",
        ylabel="steps",
        title=f"HIL round trip ({'real time' if realtime else 'lock-step'}, {sandbox}, "
        f"n={len(latencies_us)})",
    )
    try:
        atomic_write(path, lambda tmp: fig.savefig(tmp, dpi=110, bbox_inches="tight", format="png"))
    finally:
        plt.close(fig)
