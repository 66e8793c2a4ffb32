"""HIL pictures: the round-trip latency histogram (trajectories come from train.plots)."""

from __future__ import annotations

from pathlib import Path

import matplotlib

matplotlib.use("Agg")
import matplotlib.pyplot as plt

from embedrl.common import atomic_write


def plot_latency(
    latencies_us: list[float],
    path: Path,
    sandbox: str,
    realtime: bool,
    sample_time_s: float,
    watchdog_ms: float,
) -> None:
    """The round trip of every step (observation frames out -> action frame in): its distribution on a log
    axis with the median, the 99th percentile, the sample period and the node's watchdog marked, and the
    same values over the run (jitter over time)."""
    import numpy as np

    fig, (hist, over) = plt.subplots(1, 2, figsize=(12, 4), gridspec_kw={"width_ratios": [1, 1.3]})
    ms = np.asarray(latencies_us, dtype=float) / 1000
    limits = (("sample period", 1000 * sample_time_s, "tab:green"), ("node watchdog", watchdog_ms, "tab:red"))
    if ms.size:
        low = max(ms.min(), 1e-3) / 1.5
        edges = np.logspace(np.log10(low), np.log10(max(ms.max(), watchdog_ms) * 1.5), 60)
        hist.hist(ms, bins=edges, color="tab:blue")
        over.plot(np.arange(1, ms.size + 1), ms, ".", ms=2, color="tab:blue", label="round trip")
        for name, q, style in (("median", 50, "-"), ("99th percentile", 99, "--")):
            value = float(np.percentile(ms, q))
            for ax in (hist, over):
                (ax.axvline if ax is hist else ax.axhline)(value, color="k", ls=style, lw=1,
                                                           label=f"{name} {value:.3g} ms")  # fmt: skip
    for name, value, colour in limits:
        hist.axvline(value, color=colour, lw=1.5, label=f"{name} {value:g} ms")
        over.axhline(value, color=colour, lw=1.5, label=f"{name} {value:g} ms")
    mode = "real time" if realtime else "lock-step"
    hist.set(xscale="log", xlabel="round trip [ms] (log scale)", ylabel="steps",
             title=f"HIL round trip ({mode}, sandbox {sandbox}, {ms.size} steps)")  # fmt: skip
    over.set(yscale="log", xlabel="step of the run", ylabel="round trip [ms] (log scale)",
             title="round trip over the run (jitter)")  # fmt: skip
    hist.legend(fontsize=7, loc="upper center")
    over.legend(fontsize=7, loc="center left", bbox_to_anchor=(1.01, 0.5))
    fig.tight_layout()
    try:
        atomic_write(path, lambda tmp: fig.savefig(tmp, dpi=110, bbox_inches="tight", format="png"))
    finally:
        plt.close(fig)


def plot_action_differences(diffs: dict[str, list[float]], path: Path, can_rounding: float) -> None:
    """Every step's largest |node action - reference action| on a log axis, one colour per node, beside
    the tolerance and what the CAN signals' resolution alone gives."""
    import numpy as np

    from embedrl.export.verify import TOLERANCE

    fig, ax = plt.subplots(figsize=(10, 3.6))
    for node, values in diffs.items():
        shown = np.maximum(np.asarray(values, dtype=float), EXACT)
        label = f"node {node}" if len(diffs) > 1 else "node"
        ax.plot(np.arange(1, shown.size + 1), shown, ".", ms=3, label=f"{label} ({shown.size} steps)")
    ax.axhline(TOLERANCE, color="tab:red", lw=1.2, label=f"tolerance {TOLERANCE:g}")
    ax.axhline(
        can_rounding,
        color="tab:green",
        ls="--",
        lw=1,
        label=f"CAN rounding of an action {can_rounding:.1e}",
    )
    ax.set(
        yscale="log", xlabel="step of the run", ylabel=f"max |node - reference| per step\n({EXACT:g}: exact)",
        title="the node's actions against the export's reference, step by step",
    )  # fmt: skip
    ax.legend(loc="center left", bbox_to_anchor=(1.01, 0.5), fontsize="small")
    try:
        atomic_write(path, lambda tmp: fig.savefig(tmp, dpi=110, bbox_inches="tight", format="png"))
    finally:
        plt.close(fig)


EXACT = 1e-12
"""Where an exact step is drawn on the log axis."""
