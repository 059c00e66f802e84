"""A policy kind of your own (docs/policies.md): a Gaussian chunk policy on a residual MLP torso that the actor
and the critic share, sized by ``policy.options``.

    PYTHONPATH=examples ebrl up configs/quickstart.toml --set policy.kind=my_policy:ResidualPolicy
"""

from __future__ import annotations

import torch
from torch import nn

from ebrl.policies.base import GaussianChunkPolicy

OPTIONS = {"width": 64, "blocks": 2}  # policy.options this kind reads, with their defaults


class ResidualBlock(nn.Module):
    """x + W2 tanh(W1 LayerNorm(x)): keeps the gradient path short however deep the torso."""

    def __init__(self, width: int):
        super().__init__()
        self.norm = nn.LayerNorm(width)
        self.inner = nn.Sequential(nn.Linear(width, width), nn.Tanh(), nn.Linear(width, width))

    def forward(self, x: torch.Tensor) -> torch.Tensor:
        return x + self.inner(self.norm(x))


class ResidualPolicy(GaussianChunkPolicy):
    """pi(a_{t:t+K} | o_t): K x A Gaussian means and a value from one torso; a learned log-std per action."""

    def __init__(self, layout, action_dim: int, chunk: int, width: int, blocks: int, init_log_std: float):
        super().__init__()
        self.layout, self.action_dim, self.chunk = layout, action_dim, chunk
        self.torso = nn.Sequential(nn.Linear(layout.size, width), *(ResidualBlock(width) for _ in range(blocks)),
                                   nn.LayerNorm(width))
        self.mean = nn.Linear(width, chunk * action_dim)
        nn.init.zeros_(self.mean.weight)  # start near the zero action, as EBRL's own kinds do
        nn.init.zeros_(self.mean.bias)
        self.critic = nn.Linear(width, 1)
        self.log_std = nn.Parameter(torch.full((chunk * action_dim,), float(init_log_std)))

    @classmethod
    def from_config(cls, cfg, layout, action_dim, bounds):
        """The [policy] section's chunk and init_log_std, and this kind's own options (policy.options)."""
        unknown = sorted(set(cfg.options) - set(OPTIONS))
        if unknown:
            raise ValueError(f"policy.options: {unknown} are not options of {cls.__name__} ({', '.join(OPTIONS)})")
        options = {**OPTIONS, **cfg.options}
        model = cls(layout, action_dim, cfg.chunk, int(options["width"]), int(options["blocks"]), cfg.init_log_std)
        model.options = options  # what the checkpoint stores, defaults included: it rebuilds the same torso
        return model

    def moments(self, obs: torch.Tensor) -> tuple[torch.Tensor, torch.Tensor, torch.Tensor]:
        """Flat, standardised observations [B, layout.size] -> means [B, K*A], log-stds, values [B]."""
        h = self.torso(obs)
        return self.mean(h), self.log_std, self.critic(h).squeeze(-1)

    def value(self, obs: torch.Tensor) -> torch.Tensor:
        return self.critic(self.torso(self.flat(obs))).squeeze(-1)
