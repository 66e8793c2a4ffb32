"""A run folder on disk: its config, its checkpoint (written beside and swapped in, so a complete one
exists at every moment), and what resuming it checks, restores and truncates."""

from __future__ import annotations

import csv
import json
import os
import pickle
import random
import shutil
from pathlib import Path
from typing import Any

import numpy as np
import torch
from stable_baselines3.common.base_class import BaseAlgorithm
from stable_baselines3.common.off_policy_algorithm import OffPolicyAlgorithm
from stable_baselines3.common.vec_env import VecEnv, VecNormalize

from embedrl.common import atomic_write, read_json
from embedrl.train.agents import CLASSES
from embedrl.train.config import (
    Budget,
)
from embedrl.train.errors import UsageError
from embedrl.train.monitor import stop_rule_fired

CHECKPOINT_FILES = ("model.zip", "env.pkl", "random.pkl", "state.json")
"""What every checkpoint holds (plus replay_buffer.pkl for DDPG, TD3 and SAC); state.json is written last."""


def read_run_config(out: Path) -> dict[str, Any]:
    """A run directory's config.json (the run's algorithm, preset, seed, budget and overrides)."""
    from embedrl.train.config import check_run_config

    try:
        saved: dict[str, Any] = read_json(out / "config.json")
        check_run_config(saved)
    except FileNotFoundError:
        raise UsageError(f"cannot resume {out}: no config.json (not a run directory)") from None
    except (ValueError, KeyError, TypeError) as exc:
        raise UsageError(f"cannot resume {out}: config.json is damaged ({exc})") from None
    return saved


def refuse_a_fired_stop_rule(out: Path, budget: Budget) -> None:
    """A run that stopped at its stop rule would stop again at once: resuming it to a larger budget
    under the same rule is refused, naming the option that trains on (before anything is changed)."""
    try:
        state = read_json(complete_checkpoint(out) / "state.json")
        steps = int(state.get("steps", 0))
    except (OSError, ValueError, AttributeError, TypeError):
        return  # a damaged checkpoint: the checkpoint loader says what is wrong
    fired = stop_rule_fired(budget.stop, state)
    if fired is not None and budget.max_steps > steps:
        raise UsageError(
            f"{out} stopped at its stop rule (--stop {budget.stop}) at step {fired:,}; add --keep-training "
            f"to train on to {budget.max_steps:,} steps"
        )


def extend_budget(out: Path, saved: dict[str, Any], budget: Budget) -> None:
    """A resumed run may train on past its step budget (recorded in config.json's ``budget`` and
    ``extensions``); a smaller budget than the run's is refused."""
    old = int(saved["budget"].get("max_steps", 0))
    if budget.max_steps < old:
        raise UsageError(f"{out} has a budget of {old} steps; resume it with at least that many")
    old_stop = saved["budget"].get("stop", "validation")
    if budget.max_steps == old and budget.stop == old_stop:
        return
    saved["budget"] = {**saved["budget"], "max_steps": budget.max_steps, "stop": budget.stop}
    saved["extensions"] = [
        *saved.get("extensions", []),
        {
            "from_max_steps": old,
            "to_max_steps": budget.max_steps,
            "from_stop": old_stop,
            "to_stop": budget.stop,
        },
    ]
    text = json.dumps(saved, indent=2)
    atomic_write(out / "config.json", lambda tmp: tmp.write_text(text))


def complete_checkpoint(out: Path) -> Path:
    """The run's last complete checkpoint (``checkpoint/``, or ``checkpoint.old/`` if a kill came between
    the two renames of a swap); a clear error if there is none: never a silent fresh start."""
    for candidate in (out / "checkpoint", out / "checkpoint.old"):
        if (candidate / "state.json").is_file():
            return candidate
    raise UsageError(
        f"cannot resume {out}: no complete checkpoint (checkpoint/state.json); the run was stopped before "
        "its first checkpoint. Start it again with --out"
    )


def save_checkpoint(out: Path, model: BaseAlgorithm, env: VecEnv, state: dict[str, Any]) -> None:
    """Write a complete checkpoint beside the current one, then swap: a complete one always exists."""
    tmp, current, old = out / "checkpoint.partial", out / "checkpoint", out / "checkpoint.old"
    shutil.rmtree(tmp, ignore_errors=True)
    tmp.mkdir()
    model.save(tmp / "model.zip")
    if isinstance(model, OffPolicyAlgorithm):
        model.save_replay_buffer(tmp / "replay_buffer.pkl")
    with (tmp / "env.pkl").open("wb") as f:  # the env mid-episode
        pickle.dump(env.venv if isinstance(env, VecNormalize) else env, f)
    if isinstance(env, VecNormalize):  # its pickle leaves out the env it wraps
        env.save(str(tmp / "vecnormalize.pkl"))
    with (tmp / "random.pkl").open("wb") as f:
        pickle.dump(
            {
                "python": random.getstate(),
                "numpy": np.random.get_state(),
                "torch": torch.get_rng_state(),
                "action_space": model.action_space.np_random.bit_generator.state,
            },
            f,
        )
    (tmp / "state.json").write_text(json.dumps(state))  # last: its presence marks a complete checkpoint
    if current.exists():
        shutil.rmtree(old, ignore_errors=True)
        os.replace(current, old)
    os.replace(tmp, current)
    shutil.rmtree(old, ignore_errors=True)


def load_checkpoint(
    checkpoint: Path, algo: str, tb: Path, cls: type[BaseAlgorithm] | None = None
) -> tuple[BaseAlgorithm, VecEnv, dict[str, Any], dict[str, Any]]:
    """Model, training env, counters and random generators' states of a checkpoint (the run's own files:
    pickles it wrote itself)."""
    try:
        state: dict[str, Any] = read_json(checkpoint / "state.json")
        with (checkpoint / "random.pkl").open("rb") as f:
            generators: dict[str, Any] = pickle.load(f)
        with (checkpoint / "env.pkl").open("rb") as f:
            env: VecEnv = pickle.load(f)
        if (checkpoint / "vecnormalize.pkl").is_file():
            env = VecNormalize.load(str(checkpoint / "vecnormalize.pkl"), env)
        model = (cls or CLASSES[algo]).load(
            checkpoint / "model.zip", env=env, device="cpu", tensorboard_log=str(tb), force_reset=False
        )
        if isinstance(model, OffPolicyAlgorithm):
            model.load_replay_buffer(checkpoint / "replay_buffer.pkl")
    except Exception as exc:  # any damage: a truncated pickle, a bad zip, a missing file
        raise UsageError(
            f"cannot resume from {checkpoint}: it is damaged ({type(exc).__name__}: {exc}); "
            "start the run again with --out"
        ) from None
    return model, env, state, generators


def restore_random(saved: dict[str, Any], model: BaseAlgorithm) -> None:
    random.setstate(saved["python"])
    np.random.set_state(saved["numpy"])
    torch.set_rng_state(saved["torch"])
    model.action_space.np_random.bit_generator.state = saved["action_space"]


def episodes_within(curve: Path, steps: int) -> int:
    """Training episodes that ended within the first ``steps`` env steps (the random warm-up)."""
    with curve.open() as f:
        return sum(int(row["steps"]) <= steps for row in csv.DictReader(f))


def truncate_curve(path: Path, episodes: int) -> None:
    """Drop rows logged after the checkpoint: the resumed run repeats those episodes (or evaluations)."""
    rows = path.read_text().splitlines()
    path.write_text("\n".join(rows[: episodes + 1]) + "\n")
