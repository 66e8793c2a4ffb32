"""embedrl training: the warehouse environment, its scenario specs, controllers, evaluation, RL agents.

Importing this package registers ``embedrl/WarehouseRobot-v0`` with gymnasium.
"""

from gymnasium.envs.registration import register, registry

from embedrl.train.scenarios import STATIC

ENV_ID = STATIC.env_id

if ENV_ID not in registry:
    register(
        id=ENV_ID,
        entry_point="embedrl.train.warehouse_env:WarehouseRobotEnv",
        max_episode_steps=STATIC.max_steps,
    )

__all__ = ["ENV_ID"]
