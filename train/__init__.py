"""embedrl training: the environments, their scenario specs, controllers, evaluation, RL agents.

Importing this package registers the scenarios' gymnasium envs: ``embedrl/WarehouseRobot-v0`` (static),
``embedrl/WarehouseMovingShelf-v0``, ``embedrl/WarehouseTwoRobots-v0`` (the two-robot scenario from one
robot's seat, the other driven by a partner; :mod:`train.two_robots_env` has its PettingZoo Parallel env),
``embedrl/WarehouseMovingShelfPartial-v0`` (the moving shelf without its velocity) and
``embedrl/DeckWalker-v0`` (the slide deck's walking robot: MuJoCo Walker2d-v5 with the deck's reward).
"""

from gymnasium.envs.registration import register, registry

from embedrl.train.scenarios import MOVING_SHELF, MOVING_SHELF_PARTIAL, STATIC, TWO_ROBOTS, WALKER

ENV_ID = STATIC.env_id

for _spec, _entry in (
    (STATIC, "embedrl.train.warehouse_env:WarehouseRobotEnv"),
    (MOVING_SHELF, "embedrl.train.moving_shelf_env:WarehouseMovingShelfEnv"),
    (TWO_ROBOTS, "embedrl.train.two_robots_env:TwoRobotsPartnerView"),
    (MOVING_SHELF_PARTIAL, "embedrl.train.moving_shelf_env:WarehouseMovingShelfPartialEnv"),
    (WALKER, "embedrl.train.walker_env:DeckWalkerEnv"),
):
    if _spec.env_id not in registry:
        register(id=_spec.env_id, entry_point=_entry, max_episode_steps=_spec.max_steps)

__all__ = ["ENV_ID"]
