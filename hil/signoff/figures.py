"""The deployment report's figures as inline SVG: text stays text (searchable, no font files), nothing
refers outside the page."""

from __future__ import annotations

import io
from typing import Any

import matplotlib

matplotlib.use("Agg")
import matplotlib.pyplot as plt
import numpy as np

plt.rcParams["svg.fonttype"] = "none"  # labels as <text>, drawn with the reader's own sans-serif
plt.rcParams["svg.hashsalt"] = "embedrl"  # the same figure gives the same SVG (stable element ids)
plt.rcParams["font.family"] = "sans-serif"
TINY = 1e-12
"""Where an all-exact histogram is drawn (an exact match has no logarithm; the title counts them)."""


def _svg(fig: Any) -> str:
    buffer = io.StringIO()
    try:
        fig.savefig(buffer, format="svg", bbox_inches="tight", metadata={"Date": None, "Creator": None})
    finally:
        plt.close(fig)
    text = buffer.getvalue()
    return text[text.index("<svg") :]


def error_histograms(errors: dict[str, np.ndarray], tolerance: float) -> str:
    """One histogram per precision of max |C - ONNX| per sample, on a log axis, with the tolerance (none
    without a recomputed precision)."""
    if not errors:
        return ""
    fig, axes = plt.subplots(1, len(errors), figsize=(4.2 * len(errors), 3.2), squeeze=False)
    for ax, (precision, err) in zip(axes[0], errors.items(), strict=True):
        exact = int(np.sum(err == 0))
        values = np.log10(err[err > 0]) if exact < len(err) else np.array([np.log10(TINY)])
        ax.hist(values, bins=40, color="tab:blue")
        if precision == "float32":
            ax.axvline(np.log10(tolerance), color="tab:red", linestyle="--", label=f"tolerance {tolerance:g}")
            ax.legend(loc="upper left", fontsize=8)
        ax.set(
            title=f"{precision}: {len(err):,} samples, max {err.max():.2g}\n({exact:,} exact, not drawn)",
            xlabel="log10 max|C - ONNX float| per sample",
            ylabel="samples",
        )
    fig.tight_layout()
    return _svg(fig)


def closed_loop(rows: list[dict[str, Any]]) -> str:
    """Successes, collisions and timeouts per platform as stacked bars (share of episodes)."""
    fig, ax = plt.subplots(figsize=(8, 0.5 + 0.45 * len(rows)))
    labels = [r["platform"] for r in rows]
    left = np.zeros(len(rows))
    for key, color in (("successes", "tab:green"), ("collisions", "tab:red"), ("timeouts", "tab:orange")):
        share = np.array([(r[key] or 0) / max(r["episodes"] or 1, 1) for r in rows])
        ax.barh(labels, share, left=left, color=color, label=key)
        left += share
    ax.invert_yaxis()
    ax.set(xlim=(0, 1), xlabel="share of episodes")
    ax.legend(loc="center left", bbox_to_anchor=(1.02, 0.5), fontsize=8)
    return _svg(fig)


def stack_and_memory(targets: list[dict[str, Any]]) -> str:
    """Per target: stack measured vs static bound (policy_step and the firmware node), and the node
    firmware's flash and RAM against the part's."""
    fig, (stack, memory) = plt.subplots(2, 1, figsize=(9, 2 * (1.2 + 0.6 * len(targets))))
    names = [t["target"] for t in targets]
    y = np.arange(len(targets))
    measured = [t["measured"] for t in targets]
    stack.barh(
        y - 0.3,
        [m["stack_bound"]["bytes"] for m in measured],
        0.2,
        color="tab:gray",
        label="policy_step bound",
    )
    stack.barh(
        y - 0.1, [m["stack_bytes"] for m in measured], 0.2, color="tab:blue", label="policy_step painted"
    )
    stack.barh(y + 0.1, [m["node_firmware"]["stack_bound"]["bytes"] for m in measured], 0.2, color="silver",
               label="node cycle + interrupt bound")  # fmt: skip
    stack.barh(y + 0.3, [t["node_stack_peak_bytes"] or 0 for t in targets], 0.2, color="tab:cyan",
               label="node painted in HIL (0: not run)")  # fmt: skip
    stack.set(yticks=y, yticklabels=names, xlabel="stack [bytes]", title="stack: static bound vs painted")
    stack.invert_yaxis()
    stack.legend(fontsize=8, loc="center left", bbox_to_anchor=(1.02, 0.5))
    flash = [100 * m["node_firmware"]["flash_bytes"] / (1024 * m["memory_kib"]["flash"]) for m in measured]
    ram = [100 * m["node_firmware"]["image_ram_bytes"] / (1024 * m["memory_kib"]["ram"]) for m in measured]
    memory.barh(y - 0.15, flash, 0.3, color="tab:purple", label="flash")
    memory.barh(y + 0.15, ram, 0.3, color="tab:olive", label="RAM (4 KiB stack and\n8 KiB heap reserved)")
    memory.set(
        yticks=y, yticklabels=names, xlabel="% of the part", xlim=(0, 100), title="firmware node image"
    )
    memory.invert_yaxis()
    memory.legend(fontsize=8, loc="center left", bbox_to_anchor=(1.02, 0.5))
    fig.tight_layout()
    return _svg(fig)
