"""The gymnasium backend: any registered id, including ``module:EnvId`` for a user's own environments."""

from __future__ import annotations

import gymnasium as gym

from ebrl.envs.spec import EnvSpec


def build(spec: EnvSpec) -> gym.Env:
    """``gym.make(spec.id)``; ``"pkg.module:EnvId-v0"`` imports ``pkg.module`` first (gymnasium's rule)."""
    kwargs = dict(spec.kwargs)
    if spec.max_episode_steps:
        kwargs["max_episode_steps"] = spec.max_episode_steps
    return gym.make(spec.id, **kwargs)
