"""MLP Gaussian policy over action chunks: mean of K x action_dim, learned log-std, value head."""

from __future__ import annotations

import math

import numpy as np
import torch
from torch import nn
from torch.distributions import Normal


def _layer(n_in: int, n_out: int, gain: float) -> nn.Linear:
    layer = nn.Linear(n_in, n_out)
    nn.init.orthogonal_(layer.weight, gain)
    nn.init.zeros_(layer.bias)
    return layer


def _mlp(n_in: int, hidden: list[int], n_out: int, out_gain: float) -> nn.Sequential:
    layers: list[nn.Module] = []
    for width in hidden:
        layers += [_layer(n_in, width, math.sqrt(2)), nn.Tanh()]
        n_in = width
    layers.append(_layer(n_in, n_out, out_gain))
    return nn.Sequential(*layers)


class ChunkGaussianMLP(nn.Module):
    """pi(a_{t:t+K} | o_t): a diagonal Gaussian over the whole chunk; log-prob sums over K x action_dim."""

    def __init__(self, obs_dim: int, action_dim: int, chunk: int, hidden: list[int], init_log_std: float = -0.5):
        super().__init__()
        self.obs_dim, self.action_dim, self.chunk = obs_dim, action_dim, chunk
        self.actor = _mlp(obs_dim, hidden, chunk * action_dim, 0.01)
        self.critic = _mlp(obs_dim, hidden, 1, 1.0)
        self.log_std = nn.Parameter(torch.full((chunk * action_dim,), float(init_log_std)))

    def dist(self, obs: torch.Tensor) -> Normal:
        mean = self.actor(obs.reshape(obs.shape[0], -1))
        return Normal(mean, self.log_std.expand_as(mean).exp())

    def value(self, obs: torch.Tensor) -> torch.Tensor:
        return self.critic(obs.reshape(obs.shape[0], -1)).squeeze(-1)

    @torch.no_grad()
    def act(self, obs: np.ndarray) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
        """Sample chunks for a batch of observations: actions [B, K, A], log-probs [B], values [B]."""
        o = torch.as_tensor(obs, dtype=torch.float32)
        d = self.dist(o)
        a = d.sample()
        return (a.reshape(-1, self.chunk, self.action_dim).numpy(), d.log_prob(a).sum(-1).numpy(),
                self.value(o).numpy())

    def evaluate(self, obs: torch.Tensor, actions: torch.Tensor) -> tuple[torch.Tensor, torch.Tensor, torch.Tensor]:
        """Log-prob of given chunks, entropy and value, with gradients (training)."""
        d = self.dist(obs)
        flat = actions.reshape(actions.shape[0], -1)
        return d.log_prob(flat).sum(-1), d.entropy().sum(-1), self.value(obs)
