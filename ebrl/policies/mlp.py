"""MLP Gaussian policy over action chunks: mean of K x action_dim, learned log-std, value head."""

from __future__ import annotations

from typing import Any

import torch
from torch import nn
from torch.distributions import Normal

from ebrl.envs.obs import ObsLayout
from ebrl.policies.base import GaussianChunkPolicy
from ebrl.policies.nets import mlp


class ChunkGaussianMLP(GaussianChunkPolicy):
    """pi(a_{t:t+K} | o_t): a diagonal Gaussian over the whole chunk; log-prob sums over K x action_dim.

    The whole flat observation goes into two MLPs, the actor (means) and the critic (value).
    """

    kind = "mlp"

    def __init__(self, layout: ObsLayout, action_dim: int, chunk: int, hidden: list[int],
                 init_log_std: float = -0.5):
        super().__init__()
        self.layout, self.obs_dim, self.action_dim, self.chunk = layout, layout.size, action_dim, chunk
        self.actor = mlp(self.obs_dim, hidden, chunk * action_dim, 0.01)
        self.critic = mlp(self.obs_dim, hidden, 1, 1.0)
        self.log_std = nn.Parameter(torch.full((chunk * action_dim,), float(init_log_std)))

    @classmethod
    def from_config(cls, cfg: Any, layout: ObsLayout, action_dim: int, bounds: Any) -> "ChunkGaussianMLP":
        return cls(layout, action_dim, cfg.chunk, list(cfg.hidden), cfg.init_log_std)

    def dist(self, obs: torch.Tensor) -> Normal:
        """The chunk distribution for observations as the env gives them."""
        return self.heads(self.flat(obs))[0]

    def value(self, obs: torch.Tensor) -> torch.Tensor:
        return self.critic(self.flat(obs)).squeeze(-1)

    def moments(self, obs: torch.Tensor) -> tuple[torch.Tensor, torch.Tensor, torch.Tensor]:
        # obs: already flat (and standardised) by GaussianChunkPolicy
        return self.actor(obs), self.log_std, self.critic(obs).squeeze(-1)
