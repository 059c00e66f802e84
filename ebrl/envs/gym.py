"""Build environments from ``[env]``: gymnasium ids (including ``module:EnvId`` for a user's own envs),
robosuite tasks, and the optional synthetic step latency."""

from __future__ import annotations

import math
from dataclasses import dataclass, field
from typing import Any

import gymnasium as gym
import numpy as np

from ebrl.envs.obs import ObsLayout


class EnvError(ValueError):
    """An environment that cannot be built or used; the message says why."""


@dataclass(frozen=True)
class EnvSpec:
    """What a worker needs to build its environment (picklable)."""

    id: str
    backend: str = "gymnasium"
    max_episode_steps: int = 0
    kwargs: dict[str, Any] = field(default_factory=dict)
    latency: str = "none"
    latency_mean_ms: float = 16.0
    latency_sigma: float = 0.3

    @classmethod
    def from_config(cls, env_cfg: Any) -> "EnvSpec":
        return cls(id=env_cfg.id, backend=env_cfg.backend, max_episode_steps=env_cfg.max_episode_steps,
                   kwargs=dict(env_cfg.kwargs), latency=env_cfg.latency, latency_mean_ms=env_cfg.latency_mean_ms,
                   latency_sigma=env_cfg.latency_sigma)


def make_env(spec: EnvSpec, seed: int = 0) -> gym.Env:
    """Build the environment; ``"pkg.module:EnvId-v0"`` imports ``pkg.module`` first (gymnasium's rule)."""
    kwargs = dict(spec.kwargs)
    try:
        if spec.backend == "robosuite":
            from ebrl.envs.robosuite import DEFAULT_HORIZON, RobosuiteEnv

            env: gym.Env = RobosuiteEnv(spec.id, horizon=spec.max_episode_steps or DEFAULT_HORIZON, **kwargs)
        elif spec.backend == "maniskill":
            from ebrl.envs.maniskill import ManiSkillEnv

            env = ManiSkillEnv(spec.id, max_episode_steps=spec.max_episode_steps or None, **kwargs)
        else:
            if spec.max_episode_steps:
                kwargs["max_episode_steps"] = spec.max_episode_steps
            env = gym.make(spec.id, **kwargs)
    except Exception as exc:  # gymnasium, robosuite and user modules raise many kinds
        raise EnvError(f"env.id = {spec.id!r} (backend {spec.backend}): {type(exc).__name__}: {exc}") from exc
    check_spaces(spec.id, env.observation_space, env.action_space)
    if spec.latency == "lognormal":
        from ebrl.envs.latency import StepLatency

        env = StepLatency(env, spec.latency_mean_ms, spec.latency_sigma, seed=seed)
    return env


def preflight(spec: EnvSpec) -> None:
    """Fail fast, before any process starts, when the simulator cannot run on this machine (raises EnvError).
    Camera observations also decide the offscreen GL backend here, once, for every process of the run."""
    if spec.backend == "maniskill":
        from ebrl.envs.maniskill import preflight as maniskill_preflight

        maniskill_preflight(spec)
    from ebrl.envs.render import RenderingUnavailable, ensure_gl_for

    try:
        ensure_gl_for(spec)
    except RenderingUnavailable as exc:
        raise EnvError(f"env.id = {spec.id!r} (backend {spec.backend}): {exc}") from None


def check_spaces(env_id: str, obs_space: gym.Space, act_space: gym.Space) -> None:
    if not isinstance(obs_space, gym.spaces.Box):
        raise EnvError(f"{env_id}: observation space {obs_space} is not a Box (flat or image arrays are supported)")
    if not isinstance(act_space, gym.spaces.Box) or len(act_space.shape) != 1:
        raise EnvError(f"{env_id}: action space {act_space} is not a 1-d Box (continuous actions are supported)")


@dataclass(frozen=True)
class EnvInfo:
    """What gen and train need to know about the environment: spaces, observation layout, instruction."""

    observation_space: gym.spaces.Box
    action_space: gym.spaces.Box
    layout: ObsLayout
    instruction: str = ""

    @property
    def obs_shape(self) -> tuple[int, ...]:
        return tuple(self.observation_space.shape)

    @property
    def action_dim(self) -> int:
        return int(self.action_space.shape[0])


def describe(spec: EnvSpec) -> EnvInfo:
    """Build the environment once, read what policies need to know, close it. An environment may declare
    ``obs_layout`` (an :class:`ObsLayout`) and ``instruction``; otherwise its Box shape decides the layout."""
    env = make_env(spec)
    try:
        base = env.unwrapped
        layout = getattr(base, "obs_layout", None) or ObsLayout.for_shape(env.observation_space.shape)
        if layout.size != math.prod(env.observation_space.shape):
            raise EnvError(f"{spec.id}: obs_layout {layout.describe()} has {layout.size} values, "
                           f"the observation space {env.observation_space.shape}")
        return EnvInfo(env.observation_space, env.action_space, layout, getattr(base, "instruction", ""))
    finally:
        env.close()


def as_obs(obs: Any) -> np.ndarray:
    return np.asarray(obs, dtype=np.float32)
