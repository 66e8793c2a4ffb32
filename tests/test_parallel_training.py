"""``train --workers N``: Ray experience workers and one learner. One worker repeats a seed exactly; two
workers on a local two-node Ray cluster (head and worker as separate raylets) train and say how fast."""

from __future__ import annotations

import json
from pathlib import Path
from typing import Any

import pytest

from embedrl.cli import main

pytestmark = [pytest.mark.training, pytest.mark.slow]
TINY = ["--scenario", "walker", "--max-steps", "1200", "--eval-every", "1200", "--eval-episodes", "1",
        "--set", "learning_starts=1000", "--seed", "4"]  # fmt: skip


def _run(out: Path, *flags: str) -> dict[str, Any]:
    assert main(["train", "--workers", *flags, "--out", str(out), *TINY]) == 0
    return dict(json.loads((out / "summary.json").read_text()))


def test_one_worker_repeats_a_seed_exactly(tmp_path: Path) -> None:
    first, second = _run(tmp_path / "a", "1"), _run(tmp_path / "b", "1")
    assert first["total_steps"] == second["total_steps"] >= 1200 and first["updates"] == second["updates"] > 0
    curves = [(tmp_path / run / "curve.csv").read_text() for run in ("a", "b")]
    assert curves[0] == curves[1] and curves[0].count("\n") > 10
    assert first["best_validation"] == second["best_validation"]
    throughput = json.loads((tmp_path / "a" / "throughput.json").read_text())
    assert throughput["learner_updates_per_s"] > 0 and len(throughput["worker_steps_per_s"]) == 1


def test_two_workers_on_a_two_node_ray_cluster(tmp_path: Path) -> None:
    import ray
    from ray.cluster_utils import Cluster

    cluster = Cluster(initialize_head=True, head_node_args={"num_cpus": 1})
    cluster.add_node(num_cpus=2)
    try:
        cluster.wait_for_nodes()
        summary = _run(tmp_path / "run", "2", "--ray", cluster.address)
        alive = [n for n in ray.nodes() if n["Alive"]]  # type: ignore[no-untyped-call]
        assert len(alive) == 2  # the run joined the two-node cluster
    finally:
        ray.shutdown()
        cluster.shutdown()  # type: ignore[no-untyped-call]
    throughput = json.loads((tmp_path / "run" / "throughput.json").read_text())
    assert summary["workers"] == 2 and len(throughput["worker_steps_per_s"]) == 2
    assert summary["total_steps"] >= 1200 and (tmp_path / "run" / "model.zip").is_file()
    rows = (tmp_path / "run" / "curve.csv").read_text().splitlines()[1:]
    assert {row.rsplit(",", 1)[1] for row in rows} == {"0", "1"}  # both workers' episodes reached the learner
