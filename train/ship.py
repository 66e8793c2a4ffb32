"""Ship a trained policy: ``python -m embedrl.train.ship RUN_DIR NAME`` -> policies/SCENARIO/NAME.zip, .json.

The run's model (its best validated checkpoint) is evaluated deterministically in the run's scenario on 200
episodes whose seeds training never used;
below 95% success it is refused. The metadata file records the run's config, its training summary,
that evaluation and the model's SHA-256.
"""

from __future__ import annotations

import hashlib
import json
import shutil
import sys
from pathlib import Path

from embedrl.common import SHIP_TEST_SEED, provenance
from embedrl.train.evaluate import evaluate
from embedrl.train.models import load_model_policy
from embedrl.train.scenarios import DEFAULT_SCENARIO, SCENARIOS

POLICIES = Path(__file__).resolve().parents[1] / "policies"
SHIP_EPISODES = 200
MIN_SUCCESS = 0.95


def ship(run: Path, name: str) -> dict[str, object]:
    config = json.loads((run / "config.json").read_text())
    scenario = config.get("scenario", DEFAULT_SCENARIO)
    target_dir = POLICIES / scenario
    report = evaluate(
        load_model_policy(run / "model.zip"),
        SHIP_EPISODES,
        SHIP_TEST_SEED,
        name,
        env_id=SCENARIOS[scenario].env_id,
    )
    if report.success_rate < MIN_SUCCESS:
        raise SystemExit(
            f"error: {run} succeeds in {100 * report.success_rate:.1f}% < {100 * MIN_SUCCESS:.0f}%"
        )
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
        "shipped_by": provenance(),
    }
    (target_dir / f"{name}.json").write_text(json.dumps(meta, indent=2) + "\n")
    print(report.table())
    return meta


if __name__ == "__main__":
    ship(Path(sys.argv[1]), sys.argv[2])
