"""robosuite adapter: a task (Lift, ...) with state observations as a gymnasium environment.

Observations are ``robot0_proprio-state`` followed by ``object-state``; the
episode is truncated at the horizon (robosuite tasks do not terminate), and
``info["success"]`` is the task's own success check.
"""

from __future__ import annotations

import logging
from typing import Any

import gymnasium as gym
import numpy as np

DEFAULT_HORIZON = 200
OBS_KEYS = ("robot0_proprio-state", "object-state")


class RobosuiteEnv(gym.Env):
    metadata = {"render_modes": []}

    def __init__(self, task: str, horizon: int = DEFAULT_HORIZON, **kwargs: Any):
        try:
            logging.getLogger("robosuite_logs").setLevel(logging.ERROR)
            import robosuite
        except ImportError as exc:
            raise ImportError(f"env.backend = 'robosuite' needs robosuite ({exc})") from exc
        options = dict(robots="Panda", has_renderer=False, has_offscreen_renderer=False, use_camera_obs=False,
                       reward_shaping=True, control_freq=20, horizon=horizon, ignore_done=True,
                       hard_reset=False)  # a hard reset rebuilds the MuJoCo model: ~10x a step, every episode
        options.update(kwargs)
        self.env = robosuite.make(task, **options)
        self.horizon = horizon
        low, high = self.env.action_spec
        self.action_space = gym.spaces.Box(low.astype(np.float32), high.astype(np.float32), dtype=np.float32)
        obs = self._obs(self.env.reset())
        self.observation_space = gym.spaces.Box(-np.inf, np.inf, obs.shape, dtype=np.float32)
        self.t = 0

    def _obs(self, raw: dict[str, np.ndarray]) -> np.ndarray:
        return np.concatenate([np.asarray(raw[k], dtype=np.float32).ravel() for k in OBS_KEYS])

    def reset(self, *, seed: int | None = None, options: dict | None = None):
        super().reset(seed=seed)
        if seed is not None:
            np.random.seed(seed)  # robosuite's placement samplers draw from numpy's global generator
        self.t = 0
        return self._obs(self.env.reset()), {}

    def step(self, action):
        raw, reward, _, info = self.env.step(np.asarray(action, dtype=np.float64))
        self.t += 1
        info = dict(info, success=bool(self.env._check_success()))
        return self._obs(raw), float(reward), False, self.t >= self.horizon, info

    def close(self) -> None:
        self.env.close()
