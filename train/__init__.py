"""embedrl training: the warehouse environment, controllers, evaluation and (later) RL agents.

Importing this package registers ``embedrl/WarehouseRobot-v0`` with gymnasium.
"""

from gymnasium.envs.registration import register, registry

from train.warehouse_env import MAX_EPISODE_STEPS

ENV_ID = "embedrl/WarehouseRobot-v0"

if ENV_ID not in registry:
    register(
        id=ENV_ID,
        entry_point="train.warehouse_env:WarehouseRobotEnv",
        max_episode_steps=MAX_EPISODE_STEPS,
    )

__all__ = ["ENV_ID"]
