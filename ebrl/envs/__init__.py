"""Simulator adapters: build an environment from the ``[env]`` config section, run it in a worker process."""

from ebrl.envs.gym import EnvSpec, make_env, spaces
from ebrl.envs.worker import ChunkResult, EnvWorker

__all__ = ["ChunkResult", "EnvSpec", "EnvWorker", "make_env", "spaces"]
