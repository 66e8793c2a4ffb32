"""The scripted baseline proves the environment solvable, and crashing early never pays."""

from __future__ import annotations

import numpy as np

from embedrl.train.evaluate import evaluate
from embedrl.train.potential_field import PotentialFieldController


def test_potential_field_meets_the_bar_on_200_seeded_episodes() -> None:
    report = evaluate(PotentialFieldController(), episodes=200, seed=0, name="potential-field")
    assert report.success_rate >= 0.95
    assert report.mean_return >= 2.0
    assert report.successes + report.collisions + report.timeouts == 200


def test_potential_field_also_meets_the_bar_on_unseen_seeds() -> None:
    report = evaluate(PotentialFieldController(), episodes=200, seed=50_000, name="potential-field")
    assert report.success_rate >= 0.95
    assert report.mean_return >= 2.0


def test_crashing_early_is_a_worse_deal_than_a_typical_success() -> None:
    def full_ahead(obs: np.ndarray) -> np.ndarray:
        return np.ones(2, dtype=np.float32)

    crash = evaluate(full_ahead, episodes=100, seed=0, name="full ahead")
    baseline = evaluate(PotentialFieldController(), episodes=100, seed=0, name="potential-field")
    assert crash.collisions >= 95
    crash_returns = [r.episode_return for r in crash.results if r.outcome == "collision"]
    success_returns = [r.episode_return for r in baseline.results if r.outcome == "success"]
    assert max(crash_returns) < -2.0
    assert float(np.median(success_returns)) > max(crash_returns) + 4.0
    assert min(success_returns) > max(crash_returns)


def test_controller_is_a_pure_function_of_the_observation() -> None:
    pf = PotentialFieldController()
    obs = np.array([1.2, 0.4, 0.0, -1.0, 0.3, 0.1], dtype=np.float32)
    a = pf(obs)
    assert a.dtype == np.float32 and a.shape == (2,)
    assert np.all(np.abs(a) <= 1.0)
    assert pf(obs.copy()).tobytes() == a.tobytes()
