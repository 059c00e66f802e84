"""A user's own environment package, registered on import (used as env.id = "user_envs:ShortPendulum-v0")."""

import gymnasium

gymnasium.register(
    "ShortPendulum-v0",
    entry_point="gymnasium.envs.mujoco.inverted_pendulum_v5:InvertedPendulumEnv",
    max_episode_steps=10,
)


class SeedSuccess(gymnasium.Env):
    """Five steps of reward 1; ``info["success"]`` at the last step when the episode's reset seed is even (so an
    evaluation over consecutive seeds succeeds in exactly half of its episodes). Renders a grey frame."""

    metadata = {"render_modes": ["rgb_array"], "render_fps": 10}

    def __init__(self, render_mode=None):
        import numpy as np

        self.np, self.render_mode = np, render_mode
        self.observation_space = gymnasium.spaces.Box(-1.0, 1.0, (4,), np.float32)
        self.action_space = gymnasium.spaces.Box(-1.0, 1.0, (1,), np.float32)
        self.t, self.even = 0, False

    def reset(self, *, seed=None, options=None):
        super().reset(seed=seed)
        self.t, self.even = 0, seed is not None and seed % 2 == 0
        return self.np.zeros(4, self.np.float32), {}

    def step(self, action):
        self.t += 1
        done = self.t >= 5
        return self.np.full(4, self.t / 5, self.np.float32), 1.0, False, done, {"success": done and self.even}

    def render(self):
        return self.np.full((32, 48, 3), 40 * self.t, self.np.uint8)


gymnasium.register("SeedSuccess-v0", entry_point=SeedSuccess)
