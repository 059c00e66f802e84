"""gymnasium adapter: environments by id, including the ``module:EnvId`` form for a user's own envs."""

from __future__ import annotations

from dataclasses import dataclass, field
from typing import Any

import gymnasium as gym
import numpy as np


class EnvError(ValueError):
    """An environment that cannot be built or used; the message says why."""


@dataclass(frozen=True)
class EnvSpec:
    """What a worker needs to build its environment (picklable)."""

    id: str
    max_episode_steps: int = 0
    kwargs: dict[str, Any] = field(default_factory=dict)

    @classmethod
    def from_config(cls, env_cfg: Any) -> "EnvSpec":
        return cls(id=env_cfg.id, max_episode_steps=env_cfg.max_episode_steps, kwargs=dict(env_cfg.kwargs))


def make_env(spec: EnvSpec) -> gym.Env:
    """Build the environment; ``"pkg.module:EnvId-v0"`` imports ``pkg.module`` first (gymnasium's rule)."""
    kwargs = dict(spec.kwargs)
    if spec.max_episode_steps:
        kwargs["max_episode_steps"] = spec.max_episode_steps
    try:
        env = gym.make(spec.id, **kwargs)
    except (gym.error.Error, ModuleNotFoundError, ImportError) as exc:
        raise EnvError(f"env.id = {spec.id!r}: {exc}") from exc
    check_spaces(spec.id, env.observation_space, env.action_space)
    return env


def check_spaces(env_id: str, obs_space: gym.Space, act_space: gym.Space) -> None:
    if not isinstance(obs_space, gym.spaces.Box):
        raise EnvError(f"{env_id}: observation space {obs_space} is not a Box (flat or image arrays are supported)")
    if not isinstance(act_space, gym.spaces.Box) or len(act_space.shape) != 1:
        raise EnvError(f"{env_id}: action space {act_space} is not a 1-d Box (continuous actions are supported)")


def spaces(spec: EnvSpec) -> tuple[gym.spaces.Box, gym.spaces.Box]:
    """Observation and action spaces of the environment (builds it once, then closes it)."""
    env = make_env(spec)
    try:
        return env.observation_space, env.action_space
    finally:
        env.close()


def as_obs(obs: Any) -> np.ndarray:
    return np.asarray(obs, dtype=np.float32)
