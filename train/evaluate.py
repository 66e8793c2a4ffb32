"""Seeded evaluation episodes and the report format every later evaluation shares.

Episode ``i`` of an evaluation with seed ``S`` is reset with seed ``S + i``, so any two
policies evaluated with the same seed meet the same start poses episode by episode
(the exported C policy and the HIL run are compared with the Python policy this way).

In the two-robot scenario the policy drives both robots (a shared policy, one copy per robot); an
episode succeeds when both are through without a contact, and its return is the robots' mean return.
"""

from __future__ import annotations

from collections.abc import Callable
from dataclasses import asdict, dataclass, field
from typing import TYPE_CHECKING, Any

import gymnasium as gym
import numpy as np

from embedrl.common import provenance, table
from embedrl.train import ENV_ID
from embedrl.train.robot import SAMPLE_TIME
from embedrl.train.scenarios import BY_ENV_ID, team_env

if TYPE_CHECKING:
    from embedrl.train.two_robots_env import WarehouseTwoRobotsEnv

Policy = Callable[[np.ndarray], np.ndarray]
"""Observation (float32[6]) in, action (float32[2]) out."""

REPORT_KEYS = (
    "episodes",
    "successes",
    "collisions",
    "timeouts",
    "success_rate",
    "mean_return",
    "mean_time_s",
)
"""Keys every evaluation report carries (later reports add their own after these)."""

Pose = tuple[float, float, float]


@dataclass(frozen=True)
class EpisodeResult:
    """One evaluation episode."""

    seed: int
    """Seed passed to ``reset``."""
    outcome: str
    """``"success"``, ``"collision"`` or ``"timeout"``."""
    steps: int
    episode_return: float
    time_s: float
    """Simulated time: steps x sample time."""
    collided_with: str | None
    trajectory: list[Pose] = field(repr=False, default_factory=list)
    """(x, y, theta) after reset and after every step."""
    robots: tuple[str, ...] = ()
    """Two robots: each robot's outcome (``success``, ``collision``, ``timeout`` or ``stopped``: its
    episode ended because the other crashed)."""
    other_trajectories: list[list[Pose]] = field(repr=False, default_factory=list)
    """Two robots: the other robots' paths."""
    robot_returns: tuple[float, ...] = ()
    """Two robots: each robot's return."""
    distance: float | None = None
    """How far forward the robot got since reset [m], for an env whose ``info`` says (the walker's
    ``distance``); None otherwise."""
    joint_trajectory: list[tuple[float, ...]] = field(repr=False, default_factory=list)
    """The walker: its MuJoCo positions after reset and after every step (what a replay draws)."""

    @property
    def speed(self) -> float | None:
        """Mean forward speed over the episode [m/s] (None without a distance)."""
        return None if self.distance is None else self.distance / self.time_s


@dataclass(frozen=True)
class EvalReport:
    """Summary of an evaluation; ``to_json`` gives the shared report format."""

    episodes: int
    successes: int
    collisions: int
    timeouts: int
    success_rate: float
    mean_return: float
    mean_time_s: float | None
    """Mean simulated time of the successful episodes (None if there were none)."""
    std_return: float
    mean_steps: float
    seed: int
    policy: str
    results: list[EpisodeResult]
    env_id: str = ENV_ID

    @classmethod
    def from_results(
        cls, results: list[EpisodeResult], seed: int, policy: str, env_id: str = ENV_ID
    ) -> EvalReport:
        if not results:
            raise ValueError("an evaluation needs at least one episode")
        returns = np.array([r.episode_return for r in results])
        wins = [r for r in results if r.outcome == "success"]
        return cls(
            episodes=len(results),
            successes=len(wins),
            collisions=sum(r.outcome == "collision" for r in results),
            timeouts=sum(r.outcome == "timeout" for r in results),
            success_rate=len(wins) / len(results),
            mean_return=float(returns.mean()),
            mean_time_s=float(np.mean([r.time_s for r in wins])) if wins else None,
            std_return=float(returns.std()),
            mean_steps=float(np.mean([r.steps for r in results])),
            seed=seed,
            policy=policy,
            results=results,
            env_id=env_id,
        )

    def to_json(self, extra: dict[str, Any] | None = None) -> dict[str, Any]:
        """The report as JSON-ready data: summary keys, provenance, then one row per episode."""
        out: dict[str, Any] = {k: getattr(self, k) for k in REPORT_KEYS}
        spec = BY_ENV_ID.get(self.env_id)
        out.update(
            std_return=self.std_return,
            mean_steps=self.mean_steps,
            seed=self.seed,
            policy=self.policy,
            env_id=self.env_id,
            sample_time_s=SAMPLE_TIME if spec is None else spec.sample_time_s,
            **self.walking(),
            provenance=provenance(),
        )
        out.update(extra or {})
        out["per_episode"] = [
            {
                k: v
                for k, v in asdict(r).items()
                if k not in ("trajectory", "other_trajectories", "joint_trajectory")
                and not (k == "distance" and v is None)
            }
            for r in self.results
        ]
        return out

    def walking(self) -> dict[str, float]:
        """Distance and mean forward speed per episode, mean and worst, where the env reports a distance
        (``mean_distance_m``, ``min_distance_m``, ``mean_speed_m_s``, ``min_speed_m_s``); else nothing."""
        distances = [r.distance for r in self.results if r.distance is not None]
        speeds = [r.speed for r in self.results if r.speed is not None]
        if not distances:
            return {}
        return {
            "mean_distance_m": float(np.mean(distances)),
            "min_distance_m": float(np.min(distances)),
            "mean_speed_m_s": float(np.mean(speeds)),
            "min_speed_m_s": float(np.min(speeds)),
        }

    def table(self) -> str:
        """A human-readable summary table."""
        mean_time = "-" if self.mean_time_s is None else f"{self.mean_time_s:.2f}"
        rows = [
            ("policy", self.policy),
            ("episodes (seeds)", f"{self.episodes} ({self.seed}..{self.seed + self.episodes - 1})"),
            ("successes / collisions / timeouts", f"{self.successes} / {self.collisions} / {self.timeouts}"),
            ("success rate", f"{100 * self.success_rate:.1f}%"),
            ("mean return (std)", f"{self.mean_return:.4f} ({self.std_return:.4f})"),
            ("mean time of successes [s]", mean_time),
            ("mean steps", f"{self.mean_steps:.1f}"),
        ]
        walked = self.walking()
        if walked:
            rows.append(
                (
                    "distance mean / worst [m]",
                    f"{walked['mean_distance_m']:.2f} / {walked['min_distance_m']:.2f}",
                )
            )
            rows.append(
                (
                    "forward speed mean / worst [m/s]",
                    f"{walked['mean_speed_m_s']:.3f} / {walked['min_speed_m_s']:.3f}",
                )
            )
        return table(rows)


def start_episode(policy: object) -> None:
    """Start a policy with memory (one with a ``reset()`` method: a recurrent export's C, its onnxruntime
    or SB3 reference) from zero state; nothing for any other policy."""
    reset = getattr(policy, "reset", None)
    if callable(reset):
        reset()


def run_episode(
    env: gym.Env[np.ndarray, np.ndarray], policy: Policy, seed: int, sample_time: float = SAMPLE_TIME
) -> EpisodeResult:
    """Run one episode from ``reset(seed=seed)`` until it terminates or is truncated.

    The outcome comes from ``info``'s ``is_success`` and ``collided`` (an env without them only times
    out); the return is ``info["study_return"]`` where the env gives it (the reward without a shaping
    term), else the sum of rewards; ``sample_time`` converts steps to simulated time.
    """
    obs, info = env.reset(seed=seed)
    start_episode(policy)
    total, steps = 0.0, 0
    while True:
        obs, reward, terminated, truncated, info = env.step(policy(obs))
        total += float(reward)
        steps += 1
        if terminated or truncated:
            break
    return episode_result(env, seed, info, steps, float(info.get("study_return", total)), sample_time)


def episode_result(
    env: gym.Env[np.ndarray, np.ndarray],
    seed: int,
    info: dict[str, Any],
    steps: int,
    total: float,
    sample_time: float,
) -> EpisodeResult:
    """The result of an episode that just ended with ``info``: its outcome from ``is_success`` and
    ``collided`` (an env without them only times out), its trajectory if the env keeps one."""
    if info.get("is_success"):
        outcome = "success"
    elif info.get("collided"):
        outcome = "collision"
    else:
        outcome = "timeout"
    trajectory = list(getattr(env.unwrapped, "trajectory", []))
    distance = info.get("distance")
    return EpisodeResult(
        seed, outcome, steps, total, steps * sample_time, info.get("collided_with"), trajectory,
        distance=None if distance is None else float(distance),
        joint_trajectory=list(getattr(env.unwrapped, "joint_trajectory", [])),
    )  # fmt: skip


def run_two_robot_episode(env: WarehouseTwoRobotsEnv, policy: Policy, seed: int) -> EpisodeResult:
    """One two-robot episode with ``policy`` driving both robots."""
    obs, _ = env.reset(seed=seed)
    totals = dict.fromkeys(env.possible_agents, 0.0)
    steps = 0
    while env.agents:
        obs, rewards, _, _, infos = env.step({a: policy(obs[a]) for a in env.agents})
        for agent, r in rewards.items():  # the return without a shaping term where the env gives it
            totals[agent] = float(infos[agent].get("study_return", totals[agent] + float(r)))
        steps += 1
    outcomes = tuple(str(o) for o in env.outcomes)
    if env.succeeded:
        outcome = "success"
    elif "collision" in outcomes:
        outcome = "collision"
    else:
        outcome = "timeout"
    world = env._world
    hit = next((h for h in world.hits if h), None) if world is not None else None
    return EpisodeResult(
        seed,
        outcome,
        steps,
        sum(totals.values()) / len(totals),
        steps * SAMPLE_TIME,
        hit,
        list(env.trajectories[0]),
        outcomes,
        [list(t) for t in env.trajectories[1:]],
        tuple(totals[a] for a in env.possible_agents),
    )


def evaluate(
    policy: Policy,
    episodes: int,
    seed: int,
    name: str,
    progress: bool = False,
    env_id: str = ENV_ID,
    sample_time: float | None = None,
    env_kwargs: dict[str, Any] | None = None,
) -> EvalReport:
    """Evaluate ``policy`` on ``episodes`` episodes of ``env_id`` seeded ``seed, seed + 1, ...``
    (a scenario with several robots, e.g. ``embedrl/WarehouseTwoRobots-v0``: the policy drives every
    robot); an episode's time is its steps times
    ``sample_time``, by default the sample time of ``env_id``'s scenario."""
    if sample_time is None:
        spec = BY_ENV_ID.get(env_id)
        sample_time = SAMPLE_TIME if spec is None else spec.sample_time_s
    if episodes < 1:
        raise ValueError(f"episodes must be at least 1, got {episodes}")
    from tqdm import tqdm

    bar = tqdm(range(episodes), desc=f"eval {name}", unit="ep", disable=not progress)
    spec = BY_ENV_ID.get(env_id)
    if spec is not None and spec.robots > 1:
        pair = team_env(spec, **(env_kwargs or {}))
        try:
            results = [run_two_robot_episode(pair, policy, seed + i) for i in bar]
        finally:
            pair.close()
        return EvalReport.from_results(results, seed, name, env_id)
    env = gym.make(env_id, **(env_kwargs or {}))
    try:
        results = [run_episode(env, policy, seed + i, sample_time) for i in bar]
    finally:
        env.close()
    return EvalReport.from_results(results, seed, name, env_id)
