"""The report's closed-loop rows: every success rate with its episode count and a 95% interval, and a HIL
run's three questions (matches the simulation, meets the sample time, the task succeeds) kept apart."""

from __future__ import annotations

from typing import Any

import pytest

from embedrl.hil.signoff import facts


@pytest.mark.parametrize(
    ("successes", "episodes", "low", "high"),
    [(3, 3, 0.4385, 1.0), (200, 200, 0.9812, 1.0), (0, 5, 0.0, 0.4345), (45, 50, 0.7864, 0.9565)],
)
def test_the_wilson_interval(successes: int, episodes: int, low: float, high: float) -> None:
    assert facts.wilson(successes, episodes) == pytest.approx((low, high), abs=1e-4)


def _hil(**changes: Any) -> dict[str, Any]:
    report: dict[str, Any] = {
        "node": "c", "target": None, "sandbox": "uml", "episodes": 3, "successes": 3, "collisions": 0,
        "timeouts": 0, "seed": 0, "verdict": {"passed": True}, "outcomes_differing_from_simulation": [],
        "latency_us": {"p99": 5_000.0}, "sample_time_s": 0.008, "simulation": None,
    }  # fmt: skip
    return {**report, **changes}


def test_a_passing_lock_step_run_that_misses_the_sample_time_says_so() -> None:
    """The walker's firmware run: PASS in lock-step, a round trip far above the 8 ms sample time."""
    row = facts.closed_loop_rows({}, [("hil.json", _hil(latency_us={"p99": 74_000.0}))])[0]
    assert row["verdict"] is True and row["matches_simulation"] is True
    assert row["meets_sample_time"] is False and row["task_succeeds"] is True
    assert row["success"] == "3 of 3 (100%; 95% interval 44%-100%)"
    assert row["where"].endswith("no physical hardware")


def test_a_run_with_collisions_passes_but_the_task_does_not_succeed() -> None:
    """An LSTM run with 2 collisions in 5 episodes, the simulation's outcomes: it matches, the task fails."""
    row = facts.closed_loop_rows({}, [("hil.json", _hil(episodes=5, successes=3, collisions=2))])[0]
    assert row["matches_simulation"] is True and row["task_succeeds"] is False
    assert row["success"].startswith("3 of 5 (60%; 95% interval")
