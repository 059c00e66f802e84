"""Simulator adapters: build an environment from the ``[env]`` config section, run it in a worker process.

Importing this package imports no simulator: each backend's module is imported when an environment of
that backend is first built (ebrl/envs/backends.py)."""

from ebrl.envs.backends import describe, make_env, preflight
from ebrl.envs.obs import ObsField, ObsLayout, tokenize
from ebrl.envs.spec import EnvError, EnvInfo, EnvSpec
from ebrl.envs.worker import ChunkResult, EnvWorker

__all__ = ["ChunkResult", "EnvError", "EnvInfo", "EnvSpec", "EnvWorker", "ObsField", "ObsLayout", "describe",
           "make_env", "preflight", "tokenize"]
