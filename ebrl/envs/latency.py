"""A wrapper that gives any environment a configurable step latency, for controlled scheduler experiments.

A step takes the drawn latency of *CPU time* (a busy-wait on the thread's CPU
clock, counting the wrapped step itself), not of wall time: like real physics it
occupies a core, and two envs sharing one core take twice as long, so core
scheduling and pinning matter exactly as they would.
"""

from __future__ import annotations

import math
import time

import gymnasium as gym
import numpy as np


class StepLatency(gym.Wrapper):
    """Adds a lognormal step latency with the given mean (ms) and sigma (log-space)."""

    def __init__(self, env: gym.Env, mean_ms: float, sigma: float, seed: int = 0):
        super().__init__(env)
        if mean_ms <= 0 or sigma < 0:
            raise ValueError("latency_mean_ms must be > 0 and latency_sigma >= 0")
        self.mu = math.log(mean_ms / 1e3) - sigma**2 / 2  # so that E[latency] = mean_ms
        self.sigma = sigma
        self.rng = np.random.default_rng(seed)

    def step(self, action):
        deadline = time.thread_time() + self.rng.lognormal(self.mu, self.sigma)
        out = self.env.step(action)
        while time.thread_time() < deadline:
            pass
        return out
