"""HalfCheetah-v5 with CleanRL's per-env observation normalisation: the env module a user of EBRL would write today.

EBRL normalises neither observations nor returns, and a raw HalfCheetah observation mixes angles with
velocities ten times larger. With ``benchmarks/peers`` on PYTHONPATH, ``env.id =
"obs_norm:HalfCheetahObsNorm-v5"`` adds the wrappers the CleanRL-style peer uses (a running mean and
variance in each env worker, then a clip to +-10). Rewards are untouched, so returns stay comparable.
"""

import gymnasium as gym
import numpy as np


def make(**kwargs) -> gym.Env:
    env = gym.wrappers.NormalizeObservation(gym.make("HalfCheetah-v5", **kwargs))
    return gym.wrappers.TransformObservation(env, lambda obs: np.clip(obs, -10, 10).astype(np.float32),
                                             env.observation_space)


gym.register("HalfCheetahObsNorm-v5", entry_point=make)
