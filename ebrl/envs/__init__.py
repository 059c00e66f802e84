"""Simulator adapters: build an environment from the ``[env]`` config section, run it in a worker process."""

from ebrl.envs.gym import EnvError, EnvInfo, EnvSpec, describe, make_env, preflight
from ebrl.envs.obs import ObsField, ObsLayout, tokenize
from ebrl.envs.worker import ChunkResult, EnvWorker

__all__ = ["ChunkResult", "EnvError", "EnvInfo", "EnvSpec", "EnvWorker", "ObsField", "ObsLayout", "describe", "make_env", "preflight", "tokenize"]
