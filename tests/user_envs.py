"""A user's own environment package, registered on import (used as env.id = "user_envs:ShortPendulum-v0")."""

import gymnasium

gymnasium.register(
    "ShortPendulum-v0",
    entry_point="gymnasium.envs.mujoco.inverted_pendulum_v5:InvertedPendulumEnv",
    max_episode_steps=10,
)
