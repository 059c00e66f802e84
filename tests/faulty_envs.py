"""Environments that misbehave on purpose (env.id = "faulty_envs:Faulty-v0"), for the env worker tests.

One env of a fleet is picked by its reset seed (``seed % EPISODE_SEED_STRIDE``: with ``run.seed = 0``, its env
id) and ``fault`` says what it does: ``"raise"`` at every step, ``"raise-always"`` at every step and at every
reset after its first episode's, ``"sleep"`` in its first step (for ten minutes, after touching the file
``marker``), or nothing. The others are five-step episodes of reward 1."""

import time
from pathlib import Path

import gymnasium
import numpy as np

from ebrl.envs.worker import EPISODE_SEED_STRIDE


class Faulty(gymnasium.Env):
    def __init__(self, fault: str = "", bad_env: int = 0, marker: str = ""):
        self.observation_space = gymnasium.spaces.Box(-1.0, 1.0, (3,), np.float32)
        self.action_space = gymnasium.spaces.Box(-1.0, 1.0, (1,), np.float32)
        self.fault, self.bad_env, self.marker = fault, bad_env, marker
        self.bad, self.t = False, 0

    def reset(self, *, seed=None, options=None):
        super().reset(seed=seed)
        self.bad = seed is not None and seed % EPISODE_SEED_STRIDE == self.bad_env
        if self.bad and self.fault == "raise-always" and seed >= EPISODE_SEED_STRIDE:
            raise RuntimeError("this env fails at every reset after its first")
        self.t = 0
        return np.zeros(3, np.float32), {}

    def step(self, action):
        if self.bad and self.fault.startswith("raise"):
            raise RuntimeError("this env fails at every step")
        if self.bad and self.fault == "sleep":
            Path(self.marker).touch()
            time.sleep(600)
        self.t += 1
        return np.full(3, self.t / 5, np.float32), 1.0, False, self.t >= 5, {}


gymnasium.register("Faulty-v0", entry_point=Faulty)


class BuggyReward(gymnasium.Wrapper):
    """InvertedPendulum-v5 with a user's numeric bugs (``env.id = "faulty_envs:BuggyReward-v0"``): every
    ``absurd_every``-th step's reward is 1e38 (a division by a tiny number), every ``nan_every``-th NaN and every
    ``inf_every``-th -inf; every ``bad_obs_every``-th step's observation holds a NaN. Each counter runs over the
    env's whole life, so every worker hits them at its own steps."""

    def __init__(self, absurd_every: int = 3000, nan_every: int = 0, inf_every: int = 0, bad_obs_every: int = 0):
        super().__init__(gymnasium.make("InvertedPendulum-v5"))
        self.every = {"absurd": absurd_every, "nan": nan_every, "inf": inf_every, "obs": bad_obs_every}
        self.steps = 0

    def step(self, action):
        obs, reward, terminated, truncated, info = self.env.step(action)
        self.steps += 1

        def due(kind: str) -> bool:
            return bool(self.every[kind]) and self.steps % self.every[kind] == 0

        if due("absurd"):
            reward = 1e38
        elif due("nan"):
            reward = float("nan")
        elif due("inf"):
            reward = float("-inf")
        if due("obs"):
            obs = np.array(obs, np.float64)
            obs[0] = np.nan
        return obs, reward, terminated, truncated, info


gymnasium.register("BuggyReward-v0", entry_point=BuggyReward, max_episode_steps=1000)
