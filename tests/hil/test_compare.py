"""The node's actions against the reference, compared after the session (:mod:`embedrl.hil.compare`): the
same figures whether the session compares them itself or leaves its recorded steps to the host, and a
session module that loads no ONNX runtime (a guest under emulation would take its time loading one)."""

from __future__ import annotations

import json
import subprocess
import sys
from pathlib import Path
from typing import Any

import numpy as np

from embedrl.export.contract.interface_file import load_interface
from embedrl.hil import compare
from embedrl.hil.link import Stats
from embedrl.hil.session import SessionConfig, run
from embedrl.train.scenarios import STATIC

NOT_IN_A_SESSION = ("onnx", "onnxruntime", "torch", "stable_baselines3", "pettingzoo", "tqdm")
"""Packages a HIL session never needs: importing the session module loads none of them."""


class _Recurrent:
    """A policy with memory: its action is the observation's first two values plus the steps since its
    last reset (so a missed reset shows in every later difference)."""

    def __init__(self) -> None:
        self.since_reset = 0

    def reset(self) -> None:
        self.since_reset = 0

    def __call__(self, obs: np.ndarray) -> np.ndarray:
        self.since_reset += 1
        return np.asarray(obs[:, :2] * 0 + 0.01 * self.since_reset, np.float32)


def _recorded(steps: list[tuple[int, list[float], list[float]]], starts: list[int]) -> dict[str, Any]:
    stats = Stats()
    stats.exchanges = [(s, np.asarray(o), np.asarray(a, np.float32)) for s, o, a in steps]
    stats.episode_starts = starts
    carried: dict[str, Any] = json.loads(json.dumps(compare.recorded(stats)))  # as the results file has them
    return carried


def test_the_comparison_restarts_the_reference_each_episode_and_finds_the_first_divergence() -> None:
    obs = [0.0] * len(STATIC.observation)
    steps = [
        (0, obs, [0.01, 0.01]),
        (1, obs, [0.02, 0.02]),
        (2, obs, [0.01, 0.01]),  # an episode begins: the reference starts again
        (3, obs, [0.02, 0.5]),  # off by 0.48
        (4, obs, [float("nan"), 0.0]),  # a NaN action: compared as infinitely far
    ]
    results: dict[str, Any] = {
        compare.EXCHANGES: {"0": _recorded(steps, [0, 2])},
        "episodes": [{compare.EXCHANGES: [0, 0, 2]}, {compare.EXCHANGES: [0, 2, 5]}],
    }
    compare.fill(results, STATIC, _Recurrent)
    diffs = results["action_diffs"]["0"]
    assert diffs[:3] == [0.0, 0.0, 0.0] and abs(diffs[3] - 0.48) < 1e-6 and diffs[4] == float("inf")
    assert results["first_divergent_step"] == 3 and results["max_action_abs_diff"] == float("inf")
    assert [e["max_action_abs_diff"] for e in results["episodes"]] == [0.0, float("inf")]
    assert compare.EXCHANGES not in results and all(compare.EXCHANGES not in e for e in results["episodes"])


def test_a_refused_reference_action_is_compared_with_the_safe_action() -> None:
    """A correct node sends the safe action instead of one it would refuse (out of range, NaN)."""
    safe = [float(v) for v in STATIC.safe_action]
    steps = [(7, [0.0] * len(STATIC.observation), safe)]
    results: dict[str, Any] = {compare.EXCHANGES: {"0": _recorded(steps, [0])}, "episodes": []}
    compare.fill(results, STATIC, lambda: lambda obs: np.full((1, 2), 1e9, np.float32))
    assert results["action_diffs"] == {"0": [0.0]} and results["first_divergent_step"] is None


def test_a_session_left_to_the_host_to_compare_reports_the_same_figures(
    export_dir: Path, tmp_path: Path
) -> None:
    def session(compared_here: bool) -> dict[str, Any]:
        cfg = SessionConfig(
            onnx=str(export_dir / "policy.onnx"), interface=str(export_dir / "interface.json"),
            export_dir=str(export_dir), node="python", bus="virtual", iface=f"compare-{compared_here}",
            episodes=2, seed=3, results=str(tmp_path / f"{compared_here}.json"), compare=compared_here,
        )  # fmt: skip
        run(cfg)
        results: dict[str, Any] = json.loads(Path(cfg.results).read_text())
        if not compared_here:
            assert compare.EXCHANGES in results and "action_diffs" not in results
            interface = load_interface(Path(cfg.interface))
            compare.fill(results, interface, lambda: compare.reference(cfg.export_dir, cfg.onnx))
        return results

    here, on_host = session(True), session(False)
    keys = ("action_diffs", "max_action_abs_diff", "first_divergent_step")
    assert [here[k] for k in keys] == [on_host[k] for k in keys]
    assert [e["max_action_abs_diff"] for e in here["episodes"]] == [
        e["max_action_abs_diff"] for e in on_host["episodes"]
    ]
    assert here["steps"] == len(here["action_diffs"]["0"]) > 0 and here["max_action_abs_diff"] <= 1e-5


def test_the_session_module_loads_no_onnx_runtime_nor_training_packages() -> None:
    code = f"import sys, embedrl.hil.session; print([m for m in {NOT_IN_A_SESSION!r} if m in sys.modules])"
    loaded = subprocess.run([sys.executable, "-c", code], capture_output=True, text=True, check=True).stdout
    assert loaded.strip() == "[]"
