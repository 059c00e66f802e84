"""A user's env whose step cost changes while the run goes on (env.id = "phase_envs:MarkerLatency-v0").

Each step busy-waits on the CPU: ``fast_ms`` per step until the file ``marker`` exists, then a heavy-tailed
lognormal cost of mean ``slow_ms`` (sigma ``sigma``). A test creates the marker when it wants the workload to
change, so nothing depends on how fast the machine is."""

import math
import os
import time

import gymnasium
import numpy as np


class MarkerLatency(gymnasium.Env):
    def __init__(self, marker: str = "", fast_ms: float = 0.1, slow_ms: float = 3.0, sigma: float = 1.0,
                 episode_steps: int = 200):
        self.observation_space = gymnasium.spaces.Box(-1.0, 1.0, (3,), np.float32)
        self.action_space = gymnasium.spaces.Box(-1.0, 1.0, (1,), np.float32)
        self.marker, self.fast_s, self.sigma, self.episode_steps = marker, fast_ms / 1e3, sigma, episode_steps
        self.slow_mu = math.log(slow_ms / 1e3) - sigma ** 2 / 2  # lognormal of mean slow_ms
        self.slow, self.t, self.rng = False, 0, np.random.default_rng(os.getpid())

    def reset(self, *, seed=None, options=None):
        super().reset(seed=seed)
        self.t = 0
        return np.zeros(3, np.float32), {}

    def step(self, action):
        self.slow = self.slow or (bool(self.marker) and os.path.exists(self.marker))
        cost = self.rng.lognormal(self.slow_mu, self.sigma) if self.slow else self.fast_s
        end = time.thread_time() + min(cost, 0.1)
        while time.thread_time() < end:  # CPU time, as a simulator's step would take
            pass
        self.t += 1
        x = float(np.clip(action[0], -1.0, 1.0))
        return np.array([x, self.t / self.episode_steps, 0.0], np.float32), -x * x, False, \
            self.t >= self.episode_steps, {}


gymnasium.register("MarkerLatency-v0", entry_point=MarkerLatency)
