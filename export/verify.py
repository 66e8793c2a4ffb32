"""Numerical verification of each export step against the previous one.

Observations: uniform samples within the observation space's bounds plus observations recorded
from rollouts of the reference policy, at least :data:`MIN_SAMPLES` in all. Closed loop: the C
policy and the reference policy drive the warehouse env from the same seeded starts.
"""

from __future__ import annotations

import math
from collections.abc import Callable
from typing import Any

import gymnasium as gym
import numpy as np

from embedrl import train
from embedrl.common import ROLLOUT_SEED_OFFSET
from embedrl.train.evaluate import REPORT_KEYS, EvalReport, evaluate, start_episode
from embedrl.train.interface import NO_ENV
from embedrl.train.scenarios import BY_ENV_ID

TOLERANCE = 1e-5
"""Error allowed between two export steps, per output value: ``TOLERANCE x max(1, |output|)`` (absolute
for outputs up to 1, such as wheel forces; relative above, where float32 rounding grows with the
value). ``embedrl export --tolerance`` sets another."""
ROUNDING_RELATIVE_ERROR = 1e-3
"""Above this relative error a difference is not float32 rounding but an export error."""
UNIFORM_SAMPLES = 5_000
ROLLOUT_SAMPLES = 5_000
MIN_SAMPLES = 10_000
MAX_ROLLOUT_EPISODES = 1_000
"""Rollouts continue until ROLLOUT_SAMPLES observations are recorded or this many episodes ran."""
UNBOUNDED_RANGE = 10.0
"""Infinite observation bounds are sampled within +-this."""
MAX_DIFFERING_OUTCOMES = 2
"""More closed-loop episodes than this with a different outcome fail the export."""

Policy = Callable[[np.ndarray], np.ndarray]


def sample_observations(
    space: gym.spaces.Box, env_id: str, policy: Policy, seed: int
) -> tuple[np.ndarray, int]:
    """At least MIN_SAMPLES float32 observations and how many of them came from rollouts (none without
    an env: ``env_id`` :data:`~embedrl.train.interface.NO_ENV`, all uniform over the space)."""
    rng = np.random.default_rng(seed)
    low = np.where(np.isfinite(space.low), space.low, -UNBOUNDED_RANGE)
    high = np.where(np.isfinite(space.high), space.high, UNBOUNDED_RANGE)
    if env_id == NO_ENV:
        samples = rng.uniform(low, high, size=(MIN_SAMPLES, space.shape[0])).astype(np.float32)
        return samples, 0
    recorded: list[np.ndarray] = []
    env = gym.make(env_id)
    episode = 0
    while len(recorded) < ROLLOUT_SAMPLES and episode < MAX_ROLLOUT_EPISODES:
        obs, _ = env.reset(seed=seed + ROLLOUT_SEED_OFFSET + episode)
        start_episode(policy)
        episode += 1
        done = False
        while not done:
            recorded.append(np.asarray(obs, dtype=np.float32))
            obs, _, terminated, truncated, _ = env.step(policy(obs))
            done = terminated or truncated
    env.close()
    rollout = np.array(recorded, dtype=np.float32)
    if len(rollout) > ROLLOUT_SAMPLES:
        rollout = rollout[np.linspace(0, len(rollout) - 1, ROLLOUT_SAMPLES).astype(int)]
    n_uniform = max(UNIFORM_SAMPLES, MIN_SAMPLES - len(rollout))
    uniform = rng.uniform(low, high, size=(n_uniform, space.shape[0])).astype(np.float32)
    return np.concatenate([uniform, rollout]), len(rollout)


def max_abs_error(a: np.ndarray, b: np.ndarray) -> float:
    if a.shape != b.shape:
        raise ValueError(f"shapes differ: {a.shape} vs {b.shape}")
    return float(np.max(np.abs(a.astype(np.float64) - b.astype(np.float64))))


def max_ulp(a: np.ndarray, b: np.ndarray) -> int:
    """The largest distance between two float32 arrays in units in the last place: how many float32 values
    steps apart each pair is (0: the same value; +0 and -0 are the same)."""
    if a.shape != b.shape:
        raise ValueError(f"shapes differ: {a.shape} vs {b.shape}")
    if a.size == 0:
        return 0
    ordered = []
    for x in (a, b):
        bits = np.ascontiguousarray(x, np.float32).view(np.int32).astype(np.int64)
        ordered.append(np.where(bits < 0, -(bits & 0x7FFFFFFF), bits))  # float order as integers
    return int(np.max(np.abs(ordered[0] - ordered[1])))


def tolerance_failure(
    actual: np.ndarray, expected: np.ndarray, samples: np.ndarray, tolerance: float, what: str
) -> str | None:
    """None if every output of ``actual`` is within ``tolerance x max(1, |expected|)``; else the error
    message: the worst observation, the output there, the errors and what to do."""
    a, e = actual.astype(np.float64), expected.astype(np.float64)
    excess = np.abs(a - e) / np.maximum(1.0, np.abs(e))
    if not np.any(excess > tolerance) and np.all(np.isfinite(excess)):
        return None
    excess = np.where(np.isfinite(excess), excess, np.inf)
    row, col = np.unravel_index(int(np.argmax(excess)), excess.shape)
    error = abs(a[row, col] - e[row, col])
    relative = error / max(abs(e[row, col]), 1e-30)
    observation = np.array2string(samples[row], precision=4, max_line_width=10_000)
    where = (
        f"{what} by {error:.3g} at output {col} of the observation {observation}, where the output is "
        f"{e[row, col]:.6g} (relative error {relative:.2g}); allowed: {tolerance:g} x max(1, |output|)"
    )
    if relative > ROUNDING_RELATIVE_ERROR or not np.isfinite(error):
        return f"{where}. This is more than float32 rounding: an export error"
    suggested = 10.0 ** math.ceil(math.log10(float(excess[row, col])))
    return (
        f"{where}. That is float32 rounding on outputs this large: pass --tolerance {suggested:.0e}, or a "
        "narrower --obs-range if the policy never sees such observations"
    )


def supports_closed_loop(env_id: str) -> bool:
    """Closed-loop outcomes need a warehouse scenario's success/collision info."""
    return env_id in BY_ENV_ID


def closed_loop(
    reference: Policy,
    compiled: Policy,
    episodes: int,
    seed: int,
    progress: bool,
    env_id: str = train.ENV_ID,
) -> dict[str, Any]:
    """Both policies on the same seeded episodes: outcome counts and episodes whose outcome differs.

    While the C policy drives, the reference is also evaluated on every observation it sees
    (shadow mode): ``c_trajectory_max_action_diff`` separates an export error (large) from
    closed-loop amplification of float32 rounding (tiny, yet outcomes differ on long episodes).
    """
    shadow = [0.0]

    class CompiledWithShadow:
        def __call__(self, obs: np.ndarray) -> np.ndarray:
            action = compiled(obs)
            shadow[0] = max(shadow[0], max_abs_error(action, np.asarray(reference(obs), dtype=np.float32)))
            return action

        def reset(self) -> None:  # a recurrent policy: both sides start each episode from zero state
            start_episode(compiled)
            start_episode(reference)

    ref = evaluate(reference, episodes, seed, "reference", progress=progress, env_id=env_id)
    c = evaluate(CompiledWithShadow(), episodes, seed, "generated C", progress=progress, env_id=env_id)
    differing = [r.seed for r, q in zip(ref.results, c.results, strict=True) if r.outcome != q.outcome]
    return {
        "env_id": env_id,
        "episodes": episodes,
        "seed": seed,
        "reference": _summary(ref),
        "c": _summary(c),
        "c_trajectory_max_action_diff": shadow[0],
        "differing_outcomes": len(differing),
        "differing_seeds": differing,
        "max_differing_outcomes": MAX_DIFFERING_OUTCOMES,
    }


def closed_loop_failure(loop: dict[str, Any]) -> str | None:
    """The error message if the closed loop fails the export, with its diagnosis; else None."""
    if loop["differing_outcomes"] <= MAX_DIFFERING_OUTCOMES:
        return None
    shadow = loop["c_trajectory_max_action_diff"]
    if shadow > TOLERANCE:
        cause = "an export error"
    else:
        cause = (
            "float32 rounding amplified by the closed loop (long, marginal episodes); "
            "a converged policy avoids it, --episodes 0 skips the check"
        )
    return (
        f"closed loop: {loop['differing_outcomes']} of {loop['episodes']} episodes end differently with the "
        f"generated C (seeds {loop['differing_seeds'][:10]}); at most {MAX_DIFFERING_OUTCOMES} allowed. "
        f"On every observation the C saw it differs from the reference by at most {shadow:.2g}: {cause}"
    )


MAX_SUCCESS_GAP_PP = 2.0
"""A quantised policy's closed-loop success rate must stay within this of the float policy's."""


def quantized_closed_loop_failure(loop: dict[str, Any]) -> str | None:
    """The error message if a quantised policy's success rate strays from the float policy's."""
    ref, q = 100 * loop["reference"]["success_rate"], 100 * loop["c"]["success_rate"]
    if abs(ref - q) <= MAX_SUCCESS_GAP_PP:
        return None
    return (
        f"closed loop: the quantised policy succeeds in {q:.1f}% of {loop['episodes']} episodes, the float "
        f"policy in {ref:.1f}%: more than {MAX_SUCCESS_GAP_PP:g} percentage points apart"
    )


def bitwise_mismatches(a: np.ndarray, b: np.ndarray) -> int:
    """Rows of two float32 arrays that differ in any bit."""
    a32, b32 = np.ascontiguousarray(a, np.float32), np.ascontiguousarray(b, np.float32)
    return int(np.sum(np.any(a32.view(np.uint32) != b32.view(np.uint32), axis=1)))


def _summary(report: EvalReport) -> dict[str, Any]:
    return {k: getattr(report, k) for k in REPORT_KEYS}
