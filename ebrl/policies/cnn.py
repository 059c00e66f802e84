"""Vision-language Gaussian policy: conv image encoder + proprioception + instruction embedding -> chunk."""

from __future__ import annotations

from typing import Any

import torch
from torch import nn

from ebrl.envs.obs import ObsLayout
from ebrl.policies.base import GaussianChunkPolicy
from ebrl.policies.nets import ObsEncoder, layer, mlp, width


class ChunkGaussianCNN(GaussianChunkPolicy):
    """Encoder features -> tanh trunk (``hidden``) -> K x A Gaussian means and a value; learned log-std."""

    kind = "cnn"

    def __init__(self, layout: ObsLayout, action_dim: int, chunk: int, hidden: list[int], channels: list[int],
                 embed_dim: int, init_log_std: float = -0.5):
        super().__init__()
        if not layout.of_kind("image"):
            raise ValueError(f"policy.kind = \"cnn\" needs an image field in the observation; the layout "
                             f"{layout.describe()} has none (use kind \"mlp\" or \"flow\")")
        self.layout, self.action_dim, self.chunk = layout, action_dim, chunk
        self.encoder = ObsEncoder(layout, channels, embed_dim)
        self.trunk = mlp(self.encoder.out_dim, hidden, None)
        self.mean = layer(width(self.encoder.out_dim, hidden), chunk * action_dim, 0.01)
        self.critic = layer(width(self.encoder.out_dim, hidden), 1, 1.0)
        self.log_std = nn.Parameter(torch.full((chunk * action_dim,), float(init_log_std)))

    @classmethod
    def from_config(cls, cfg: Any, layout: ObsLayout, action_dim: int, bounds: Any) -> "ChunkGaussianCNN":
        return cls(layout, action_dim, cfg.chunk, list(cfg.hidden), list(cfg.channels), cfg.embed_dim,
                   cfg.init_log_std)

    def moments(self, obs: torch.Tensor) -> tuple[torch.Tensor, torch.Tensor, torch.Tensor]:
        h = self.trunk(self.encoder(obs))
        return self.mean(h), self.log_std, self.critic(h).squeeze(-1)

    def value(self, obs: torch.Tensor) -> torch.Tensor:
        return self.critic(self.trunk(self.encoder(self.flat(obs)))).squeeze(-1)
