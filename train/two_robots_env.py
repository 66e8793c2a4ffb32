"""The two-robot scenario as a PettingZoo Parallel env: two robots, one gap."""

from __future__ import annotations

import math
from typing import Any

import gymnasium as gym
import numpy as np
from gymnasium import spaces
from gymnasium.utils import seeding
from pettingzoo import ParallelEnv

from embedrl.train import layout, rewards
from embedrl.train.robot import PHYSICS_SUBSTEPS, SAMPLE_TIME
from embedrl.train.scenarios import TWO_ROBOTS
from embedrl.train.world import ObsBounds, Pose, World, checked_pose, held_action

AGENTS = ("robot_0", "robot_1")
_BOUNDS = ObsBounds(TWO_ROBOTS.obs_low, TWO_ROBOTS.obs_high)
NAME = "warehouse_two_robots_v0"

Obs = dict[str, np.ndarray]


class WarehouseTwoRobotsEnv(ParallelEnv):  # type: ignore[misc]
    """Two robots start at opposite ends of the shelves and must both pass down through the one gap.

    ## Description
    The static warehouse (map, robot, physics, 0.3 s sample time) with two robots, ``robot_0`` and
    ``robot_1``. At reset ``robot_0`` is placed beside the shelves on a random side and ``robot_1`` on the
    other side, each with the static scenario's start distribution. A robot whose centre passes below
    y = -0.15 m is through: it drives on out of the arena (it is removed from the world, so it never
    blocks the other robot: the study's "success line with room") and its agent is done. Any contact (a
    shelf, a wall or the other robot) ends the episode for both.

    ## Action Space
    Per robot ``Box(-1, 1, (2,), float32)``, held for one sample time (0.3 s):

    | Num | Action                    | Min | Max |
    |-----|---------------------------|-----|-----|
    | 0   | left wheel force ``F_L``  | -1  | 1   |
    | 1   | right wheel force ``F_R`` | -1  | 1   |

    ## Observation Space
    Per robot ``Box(float32, (12,))``: its own state as in the static env, then the other robot relative
    to it (map axes). Once the other robot is through, observations 6-11 are 0.

    | Num | Observation                                      | Min   | Max  | Unit  |
    |-----|--------------------------------------------------|-------|------|-------|
    | 0   | x, position along the shelves                    | -1.8  | 1.8  | m     |
    | 1   | y, position across the shelves                   | -0.15 | 1.3  | m     |
    | 2   | sin(theta), heading (0 = along +x)               | -1    | 1    |       |
    | 3   | cos(theta)                                       | -1    | 1    |       |
    | 4   | v, forward speed                                 | -0.7  | 0.7  | m/s   |
    | 5   | w, turn rate (counter-clockwise)                 | -2.0  | 2.0  | rad/s |
    | 6   | other robot x minus own x                        | -3.6  | 3.6  | m     |
    | 7   | other robot y minus own y                        | -1.45 | 1.45 | m     |
    | 8   | other robot sin(theta)                           | -1    | 1    |       |
    | 9   | other robot cos(theta)                           | -1    | 1    |       |
    | 10  | other robot forward speed                        | -0.7  | 0.7  | m/s   |
    | 11  | 1 while the other robot is in the arena, else 0  | 0     | 1    |       |

    ## Rewards
    Per robot, on its own state after the step: ``reward="thesis"`` is the study's eq. 19 with the
    success bonus ``success_bonus`` (5, or the study's other variant 20); ``reward="potential-field"``
    the study's two-robot reward, whose contours surround every obstacle *and the other robot*, averaged
    over the robot's four corners; ``reward="shaped"`` adds potential-based shaping towards the gap to
    eq. 19 (:mod:`train.rewards`). A robot that touches something gets -2; a robot
    whose episode ends because the other one crashed gets no penalty (it is truncated, not terminated).

    ## Starting State
    As above; ``reset(options={"start_poses": ((x0, y0, theta0), (x1, y1, theta1))})`` fixes both.

    ## Episode End
    - A robot through the gap: that robot terminates (``is_success``), the other goes on.
    - A contact: the robot(s) that touched something terminate (``collided``, ``collided_with`` names it,
      e.g. ``robot 1``); the other is truncated.
    - 200 steps (60 s): every robot still in the arena is truncated.

    The episode succeeds when both robots are through without a contact.

    ## Arguments
    ``WarehouseTwoRobotsEnv(render_mode="rgb_array", reward="thesis", success_bonus=5.0)``

    ## Version History
    - v0: initial version.
    """

    metadata: dict[str, Any] = {  # noqa: RUF012 (PettingZoo API)
        "name": NAME,
        "render_modes": ["rgb_array"],
        "render_fps": 1 / SAMPLE_TIME,
    }

    SPEC = TWO_ROBOTS

    def __init__(
        self,
        render_mode: str | None = None,
        reward: str = "thesis",
        success_bonus: float = rewards.SUCCESS_BONUS,
        shaping_gamma: float = rewards.SHAPING_GAMMA,
        shaping_gain: float = rewards.SHAPING_GAIN,
    ) -> None:
        if render_mode is not None and render_mode not in self.metadata["render_modes"]:
            raise ValueError(
                f"render_mode {render_mode!r} is not supported; use one of {self.metadata['render_modes']}"
            )
        rewards.check_options(reward, success_bonus, shaping_gain)
        self.render_mode = render_mode
        self.reward_name = reward
        self.success_bonus = success_bonus
        self.shaping_gamma = shaping_gamma
        self.shaping_gain = shaping_gain
        self.possible_agents = list(AGENTS)
        self.agents: list[str] = []
        self._obs_space = spaces.Box(TWO_ROBOTS.obs_low, TWO_ROBOTS.obs_high, dtype=np.float32)
        self._act_space = spaces.Box(TWO_ROBOTS.act_low, TWO_ROBOTS.act_high, dtype=np.float32)
        self._np_random, _ = seeding.np_random(None)
        self._world: World | None = None
        self._phi = [0.0, 0.0]
        """Each robot's shaping potential before the step (``reward="shaped"``)."""
        self._study_returns = [0.0, 0.0]
        """Each robot's return so far without the shaping term (``info["study_return"]``)."""
        self._steps = 0
        self.trajectories: list[list[Pose]] = [[], []]
        """Each robot's (x, y, theta) after reset and after every step it was in the arena."""
        self.outcomes: list[str | None] = [None, None]
        """Per robot: ``"success"``, ``"collision"``, ``"timeout"`` or ``"stopped"`` (the other crashed)."""

    def observation_space(self, agent: str) -> spaces.Box:
        return self._obs_space

    def action_space(self, agent: str) -> spaces.Box:
        return self._act_space

    # -- observations ----------------------------------------------------------------------------

    def _observe(self, i: int) -> np.ndarray:
        world = self._world
        assert world is not None
        x, y, s, c, v, w = world.robot_state(i)
        j = 1 - i
        if world.active[j]:
            ox, oy, os_, oc, ov, _ = world.robot_state(j)
            other = (ox - x, oy - y, os_, oc, ov, 1.0)
        else:
            other = (0.0, 0.0, 0.0, 0.0, 0.0, 0.0)
        return _BOUNDS.clip((x, y, s, c, v, w, *other))

    def _info(self, i: int) -> dict[str, Any]:
        assert self._world is not None
        return {
            "is_success": self.outcomes[i] == "success",
            "collided": self.outcomes[i] == "collision",
            "collided_with": self._world.hits[i],
            "study_return": self._study_returns[i],
        }

    # -- PettingZoo API --------------------------------------------------------------------------

    def reset(
        self, seed: int | None = None, options: dict[str, Any] | None = None
    ) -> tuple[Obs, dict[str, Any]]:
        if seed is not None:
            self._np_random, _ = seeding.np_random(seed)
        # Other option keys are ignored (PettingZoo's API test passes arbitrary ones).
        given = (options or {}).get("start_poses")
        if given is not None:
            if len(given) != 2:
                raise ValueError(f"start_poses must be two poses, got {given!r}")
            poses = [checked_pose(p) for p in given]
        else:
            rng = self._np_random
            side = 1.0 if rng.random() < 0.5 else -1.0
            poses = []
            for sign in (side, -side):
                x = sign * rng.uniform(layout.START_X_MIN, layout.START_X_MAX)
                y = rng.uniform(layout.START_Y_MIN, layout.START_Y_MAX)
                poses.append((x, y, rng.uniform(-math.pi, math.pi)))
        if self._world is None:
            world = World(poses)
        else:
            world = self._world
            world.reset(poses)
        for i in range(2):
            overlaps = world.overlaps(i)
            if overlaps:
                self._world = None  # a failed reset leaves no episode to step
                raise ValueError(f"start pose {poses[i]} of {AGENTS[i]} overlaps {', '.join(overlaps)}")
        self._world = world
        self._steps = 0
        self.agents = list(AGENTS)
        self.trajectories = [[poses[0]], [poses[1]]]
        self._phi = [rewards.potential(p[0], p[1], self.shaping_gain) for p in poses]
        self._study_returns = [0.0, 0.0]
        self.outcomes = [None, None]
        return {a: self._observe(i) for i, a in enumerate(AGENTS)}, {
            a: self._info(i) for i, a in enumerate(AGENTS)
        }

    def step(
        self, actions: dict[str, np.ndarray]
    ) -> tuple[Obs, dict[str, float], dict[str, bool], dict[str, bool], dict[str, dict[str, Any]]]:
        world = self._world
        if world is None or not self.agents:
            raise RuntimeError("call reset() before step() (and after the episode ended)")
        missing = set(self.agents) - set(actions)
        if missing:
            raise ValueError(f"no action for {sorted(missing)}")
        acting = list(self.agents)
        forces: list[np.ndarray | None] = [None, None]
        for i, agent in enumerate(AGENTS):
            if agent in acting:
                forces[i] = held_action(actions[agent], f"action of {agent}")
        through = [False, False]
        world.hold(forces)
        for _ in range(PHYSICS_SUBSTEPS):
            world.substep()
            if any(h is not None for h in world.hits):
                break
            for i in range(2):
                if world.active[i] and world.y(i) < layout.GOAL_Y:
                    through[i] = True
                    world.remove(i)  # it drives on out of the arena
        self._steps += 1
        crashed = any(h is not None for h in world.hits)
        timeout = self._steps >= TWO_ROBOTS.max_steps
        obs, rew, term, trunc, infos = {}, {}, {}, {}, {}
        poses = [world.pose(i) for i in range(2)]
        for i, agent in enumerate(AGENTS):
            if agent not in acting:
                continue
            collided = world.hits[i] is not None
            made_it = through[i] and not collided
            if collided:
                self.outcomes[i] = "collision"
            elif made_it:
                self.outcomes[i] = "success"
            elif crashed:
                self.outcomes[i] = "stopped"
            elif timeout:
                self.outcomes[i] = "timeout"
            self.trajectories[i].append(poses[i])
            obs[agent] = self._observe(i)
            force = forces[i]
            assert force is not None
            w = float(obs[agent][5])
            if self.reward_name in ("thesis", "shaped"):
                x, y = float(obs[agent][0]), float(obs[agent][1])
                rew[agent] = rewards.thesis(x, y, w, force, made_it, collided, self.success_bonus)
                self._study_returns[i] += rew[agent]
                if self.reward_name == "shaped":
                    phi = rewards.potential(poses[i][0], poses[i][1], self.shaping_gain)
                    rew[agent] += rewards.shaping(self._phi[i], phi, collided or made_it, self.shaping_gamma)
                    self._phi[i] = phi
            else:
                others = [poses[1 - i]] if world.active[1 - i] else []
                rew[agent] = rewards.potential_field(
                    poses[i], w, force, made_it, collided, layout.OBSTACLES, others, self.success_bonus
                )
                self._study_returns[i] += rew[agent]
            term[agent] = collided or made_it
            trunc[agent] = not term[agent] and (crashed or timeout)
            infos[agent] = self._info(i)
        self.agents = [a for a in acting if not (term[a] or trunc[a])]
        return obs, rew, term, trunc, infos

    @property
    def succeeded(self) -> bool:
        """Both robots through without a contact (meaningful once the episode has ended)."""
        return self.outcomes == ["success", "success"]

    def render(self) -> np.ndarray | None:
        if self.render_mode is None:
            gym.logger.warn("render() called without render_mode; use render_mode='rgb_array'")
            return None
        from embedrl.train.rendering import draw_frame

        return draw_frame(self.trajectories[0], others=[self.trajectories[1]])

    def close(self) -> None:
        self._world = None


def parallel_env(**kwargs: Any) -> WarehouseTwoRobotsEnv:
    """PettingZoo's conventional constructor."""
    return WarehouseTwoRobotsEnv(**kwargs)


class TwoRobotsPartnerView(gym.Env[np.ndarray, np.ndarray]):
    """``embedrl/WarehouseTwoRobots-v0``: the two-robot scenario as a single-agent gymnasium env.

    The agent drives ``robot_0``; ``robot_1`` is driven by ``partner`` (an observation-to-action
    callable; default the potential-field controller). Spaces, rewards and ends are ``robot_0``'s in
    :class:`WarehouseTwoRobotsEnv`, except that the episode goes on until both robots are done: once
    ``robot_0`` is through, steps pass (its actions ignored, reward 0) until the partner finishes, and
    ``is_success`` means both robots are through. Shared-policy training does not use this view (it uses
    :class:`~train.shared_policy.SharedPolicyVecEnv`); evaluation of a shared policy drives both robots
    with it (:func:`train.evaluate.evaluate`).
    """

    metadata = {"render_modes": ["rgb_array"], "render_fps": 1 / SAMPLE_TIME}  # noqa: RUF012

    def __init__(
        self,
        render_mode: str | None = None,
        reward: str = "thesis",
        success_bonus: float = rewards.SUCCESS_BONUS,
        partner: Any = None,
    ) -> None:
        self.parallel = WarehouseTwoRobotsEnv(render_mode, reward, success_bonus)
        self.render_mode = render_mode
        if partner is None:
            from embedrl.train.potential_field import PotentialFieldController

            partner = PotentialFieldController(scenario=TWO_ROBOTS.name)
        self.partner = partner
        self.observation_space = self.parallel.observation_space(AGENTS[0])
        self.action_space = self.parallel.action_space(AGENTS[0])
        self._obs: Obs = {}

    @property
    def trajectory(self) -> list[Pose]:
        return self.parallel.trajectories[0]

    def reset(
        self, *, seed: int | None = None, options: dict[str, Any] | None = None
    ) -> tuple[np.ndarray, dict[str, Any]]:
        super().reset(seed=seed)
        self._obs, infos = self.parallel.reset(seed=seed, options=options)
        return self._obs[AGENTS[0]], infos[AGENTS[0]]

    def step(self, action: np.ndarray) -> tuple[np.ndarray, float, bool, bool, dict[str, Any]]:
        env = self.parallel
        actions = {AGENTS[0]: action, AGENTS[1]: self.partner(self._obs[AGENTS[1]])}
        obs, rew, _, _, _ = env.step({a: actions[a] for a in env.agents})
        self._obs.update(obs)
        mine = AGENTS[0]
        done = not env.agents
        info = {
            "is_success": done and env.succeeded,
            "collided": "collision" in env.outcomes,
            "collided_with": next((h for h in env._world.hits if h), None) if env._world else None,
        }
        terminated = done and all(o in ("success", "collision") for o in env.outcomes)
        return self._obs[mine], float(rew.get(mine, 0.0)), terminated, done and not terminated, info

    def render(self) -> np.ndarray | None:
        return self.parallel.render()

    def close(self) -> None:
        self.parallel.close()
