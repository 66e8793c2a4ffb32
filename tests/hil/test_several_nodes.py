"""Several nodes on one bus: each node its own IDs (policy_node --node-id k), one robot each, in lock-step.
The same test on the Python nodes (virtual bus, fast) and on the C nodes over vcan (slow)."""

from __future__ import annotations

from pathlib import Path
from typing import Any

import numpy as np
import pytest

from embedrl.hil.sandbox import Guest
from embedrl.hil.session import NODE_SEED_STRIDE
from tests.hil.helpers import hil

NODES, EPISODES = 2, 2


def _check(report: dict[str, Any], log: Path) -> None:
    assert report["episodes"] == NODES * EPISODES and report["faults"] == 0
    assert [(r["node"], r["seed"]) for r in report["per_episode"]] == [
        (k, i + k * NODE_SEED_STRIDE) for i in range(EPISODES) for k in range(NODES)
    ]
    assert report["outcomes_differing_from_simulation"] == []
    assert report["successes"] == report["simulation"]["successes"]
    assert report["max_action_abs_diff"] <= 1e-5
    assert all(n["episodes"] == EPISODES for n in report["per_node"].values())
    assert [n["node_id"] for n in report["nodes"]] == [0, 1]
    assert all(n["status"]["frames_ok"] > 0 and n["diag"]["stale_steps"] == 0 for n in report["nodes"])
    assert report["frames_tx"] == 3 * (report["steps"] + report["retries"])
    assert report["verdict"]["passed"], report["verdict"]
    ids = {line.split()[2].split("#")[0] for line in log.read_text().splitlines()}
    # node 0: 0x100-0x102, 0x200, 0x300/0x301; node 1 the same + 0x20 (status + 2)
    assert ids == {"100", "101", "102", "200", "300", "301", "120", "121", "122", "220", "302", "303"}


def test_two_python_nodes_on_one_virtual_bus(export_dir: Path, tmp_path: Path) -> None:
    log = tmp_path / "frames.log"
    report = hil(None, export_dir, tmp_path, "--node", "python", "--nodes", str(NODES), "--episodes",
                 str(EPISODES), "--log", str(log))  # fmt: skip
    _check(report, log)


@pytest.mark.slow
def test_two_c_nodes_on_one_vcan(guest: Guest, export_dir: Path, tmp_path: Path) -> None:
    log = tmp_path / "frames.log"
    report = hil(
        guest, export_dir, tmp_path, "--nodes", str(NODES), "--episodes", str(EPISODES), "--log", str(log)
    )
    _check(report, log)


def test_the_map_of_several_nodes_tells_them_apart(export_dir: Path, tmp_path: Path) -> None:
    """Each node's robot: its own line style and start marker, named in the legend; one node: plain paths."""
    import matplotlib.pyplot as plt

    from embedrl.train.evaluate import EpisodeResult, EvalReport
    from embedrl.train.plots import NODE_STYLES, trajectory_figure

    path = [(0.0, -2.0, 0.0), (0.1, -1.0, 0.0), (0.0, 1.0, 0.0)]
    results = [EpisodeResult(s, "success", 3, 1.0, 0.9, None, path) for s in (0, 0, 1, 1)]
    report = EvalReport.from_results(results, 0, "HIL")
    fig = trajectory_figure(report, nodes=[0, 1, 0, 1])
    ax = fig.axes[0]
    paths = [line for line in ax.lines if np.size(line.get_xdata()) == 3]
    styles = {(line.get_linestyle(), line.get_color()) for line in paths}
    assert styles == {("-", "tab:green"), ("--", "tab:green")}
    legend = ax.get_legend()
    assert legend is not None
    labels = [t.get_text() for t in legend.get_texts()]
    assert "node 0: start, path" in labels and "node 1: start, path" in labels and "start" not in labels
    assert NODE_STYLES[1] == ("--", "s")
    plt.close(fig)
    fig = trajectory_figure(report, nodes=[0, 0, 0, 0])
    legend = fig.axes[0].get_legend()
    assert legend is not None and "start" in [t.get_text() for t in legend.get_texts()]
    plt.close(fig)
    report_json = hil(None, export_dir, tmp_path, "--node", "python", "--nodes", "2", "--episodes", "1",
                      "--plot", str(tmp_path / "plots"))  # fmt: skip
    assert report_json["episodes"] == 2 and (tmp_path / "plots" / "hil_trajectories.png").is_file()
