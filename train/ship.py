"""Ship a trained policy: ``python -m embedrl.train.ship RUN_DIR NAME`` -> policies/SCENARIO/NAME.zip, .json.

The run's model (its best validated checkpoint) is evaluated deterministically in the run's scenario on 200
episodes whose seeds training never used;
below 95% success it is refused. The walker's gate is the deck's: on 50 such episodes, at least 90% walk the
whole episode without a fall at a mean forward speed of at least 1 m/s. The metadata file records the run's
config, its training summary, that evaluation and the model's SHA-256.
"""

from __future__ import annotations

import hashlib
import json
import shutil
import sys
from pathlib import Path

from embedrl.common import SHIP_TEST_SEED, provenance
from embedrl.train.evaluate import EvalReport, evaluate
from embedrl.train.models import load_model_policy
from embedrl.train.scenarios import DEFAULT_SCENARIO, SCENARIOS, WALKER

POLICIES = Path(__file__).resolve().parents[1] / "policies"
SHIP_EPISODES = 200
MIN_SUCCESS = 0.95
WALKER_EPISODES = 50
WALKER_MIN_SPEED = 1.0
"""m/s: the deck's walking speed."""
WALKER_MIN_SHARE = 0.90


def walking_episodes(report: EvalReport) -> int:
    """Episodes that ran to the step limit without a fall at a mean forward speed of at least 1 m/s."""
    return sum(r.outcome == "success" and (r.speed or 0.0) >= WALKER_MIN_SPEED for r in report.results)


def ship(run: Path, name: str) -> dict[str, object]:
    config = json.loads((run / "config.json").read_text())
    scenario = config.get("scenario", DEFAULT_SCENARIO)
    target_dir = POLICIES / scenario
    walker = scenario == WALKER.name
    report = evaluate(
        load_model_policy(run / "model.zip"),
        WALKER_EPISODES if walker else SHIP_EPISODES,
        SHIP_TEST_SEED,
        name,
        env_id=SCENARIOS[scenario].env_id,
        sample_time=SCENARIOS[scenario].sample_time_s,
    )
    share = walking_episodes(report) / report.episodes if walker else report.success_rate
    floor = WALKER_MIN_SHARE if walker else MIN_SUCCESS
    if share < floor:
        what = "walks without a fall at >= 1 m/s" if walker else "succeeds"
        raise SystemExit(f"error: {run} {what} in {100 * share:.1f}% < {100 * floor:.0f}%")
    target_dir.mkdir(parents=True, exist_ok=True)
    target = target_dir / f"{name}.zip"
    shutil.copyfile(run / "model.zip", target)
    if (run / "vecnormalize.npz").is_file():
        shutil.copyfile(run / "vecnormalize.npz", target_dir / f"{name}_vecnormalize.npz")
    meta = {
        "model": target.name,
        "sha256": hashlib.sha256(target.read_bytes()).hexdigest(),
        "config": config,
        "training": json.loads((run / "summary.json").read_text()),
        "evaluation": report.to_json() | {"per_episode": None},
        **(
            {
                "walking": {
                    "episodes": report.episodes,
                    "without_fall_at_1_m_s": walking_episodes(report),
                    "share": share,
                }
            }
            if walker
            else {}
        ),
        "shipped_by": provenance(),
    }
    (target_dir / f"{name}.json").write_text(json.dumps(meta, indent=2) + "\n")
    print(report.table())
    return meta


if __name__ == "__main__":
    ship(Path(sys.argv[1]), sys.argv[2])
