"""What an environment is, whatever simulator runs it: the spec a worker builds it from, the info policies
read from it, and the error for one that cannot be built. Imports no simulator (a leaf of ebrl.envs)."""

from __future__ import annotations

from dataclasses import dataclass, field
from typing import TYPE_CHECKING, Any

import numpy as np

from ebrl.envs.obs import ObsLayout
from ebrl.envs.records import backend_record

if TYPE_CHECKING:
    import gymnasium as gym


class EnvError(ValueError):
    """An environment that cannot be built or used; the message says why."""


@dataclass(frozen=True)
class EnvSpec:
    """What a worker needs to build its environment (picklable); ``backend`` names a record of
    ``ebrl.envs.records.BACKENDS``."""

    id: str
    backend: str = "gymnasium"
    max_episode_steps: int = 0
    kwargs: dict[str, Any] = field(default_factory=dict)
    latency: str = "none"
    latency_mean_ms: float = 16.0
    latency_sigma: float = 0.3
    max_abs_reward: float = 1e6  # per env step: beyond it a reward is clipped (ebrl.envs.guard)
    obs_keys: tuple[str, ...] = ()  # a Dict observation's key paths, selected and ordered (ebrl.envs.dictobs)
    lazy_render: bool = True  # render only the observations read (the schedule's sim.lazy_render), where it can

    @property
    def gpu_physics(self) -> bool:
        """Whether the simulator steps on the GPU (its record's ``gpu_physics``: ManiSkill under ``sim_backend =
        "physx_cuda[:N]"``, MuJoCo Warp on a CUDA device): a whole batch of envs per process."""
        return backend_record(self.backend).gpu_physics(self.kwargs)

    @classmethod
    def from_config(cls, env_cfg: Any) -> "EnvSpec":
        return cls(id=env_cfg.id, backend=env_cfg.backend, max_episode_steps=env_cfg.max_episode_steps,
                   kwargs=dict(env_cfg.kwargs), latency=env_cfg.latency, latency_mean_ms=env_cfg.latency_mean_ms,
                   latency_sigma=env_cfg.latency_sigma, max_abs_reward=env_cfg.max_abs_reward,
                   obs_keys=tuple(env_cfg.obs_keys))


@dataclass(frozen=True)
class EnvInfo:
    """What gen and train need to know about the environment: spaces, observation layout, instruction."""

    observation_space: gym.spaces.Box
    action_space: gym.spaces.Box
    layout: ObsLayout
    instruction: str = ""
    reward_range: tuple[float, float] | None = None  # an env step's reward, where the env declares it (finite)

    @property
    def obs_shape(self) -> tuple[int, ...]:
        return tuple(self.observation_space.shape)

    @property
    def action_dim(self) -> int:
        return int(self.action_space.shape[0])

    @property
    def bounds(self) -> tuple[np.ndarray, np.ndarray]:
        """The action space's (low, high), float64 (a bounded policy kind scales into them)."""
        return np.asarray(self.action_space.low, np.float64), np.asarray(self.action_space.high, np.float64)
