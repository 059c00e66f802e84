"""Flow-matching action head: the K-step chunk by N Euler steps from noise, with an exact log-prob for PPO.

Sampling a chunk for observation o (features f = encoder(o)), with t_i = i / N:

    x_0 ~ N(0, I)                                          shape [K, A]: the latents
    x_{i+1} = x_i + v(x_i, t_i, f) / N                     i = 0 .. N-2, deterministic
    mu = x_{N-1} + v(x_{N-1}, t_{N-1}, f) / N              the last Euler step's result ...
    a ~ N(mu, diag(sigma^2))                               ... is the mean of a Gaussian

v is the velocity MLP (input: flattened x_t, a sinusoidal embedding of t, f);
log sigma is one learned parameter per action dimension of the chunk, starting
at ``policy.init_log_std``. Given o and x_0 every step before the last is a
deterministic function, so mu(o, x_0) is deterministic and

    log pi(a | o, x_0) = log N(a; mu(o, x_0), sigma^2)

is an exact Gaussian log-prob, not an estimate. Generation returns x_0 as the
latents; training re-runs the chain from the stored x_0 with gradients (they
flow through all N velocity-net calls) and gets the same log-prob generation
reported. Since x_0 is drawn independently of the parameters, the policy
gradient and the PPO ratio of the noise-conditioned policy pi(a | o, x_0) are
valid for the objective. The entropy reported is that of the final Gaussian,
H(a | o, x_0), a lower bound of the entropy of the marginal pi(a | o).

This is the noise-injection idea of ReinFlow (Zhang et al., 2025, arXiv:2505.22094)
and of Flow-Noise in piRL (Chen et al., 2025, arXiv:2510.25889), which add learned
noise at every denoising step and sum the per-step Gaussian log-probs (storing
the whole chain); here only the final step is stochastic, so the latents are
just x_0 and the cost of a log-prob is one deterministic pass of the chain.

N (``policy.denoise_steps``) sets the cost of a chunk (N velocity-net calls),
never the parameters: weights trained or saved with one N load with any other.
"""

from __future__ import annotations

import math
from typing import Any

import numpy as np
import torch
from torch import nn
from torch.distributions import Normal

from ebrl.envs.obs import ObsLayout
from ebrl.policies.base import ChunkPolicy, Tensors3, noise
from ebrl.policies.nets import ObsEncoder, mlp
from ebrl.policies.transformer import TransformerEncoder

TIME_FREQUENCIES = 8  # the time embedding is [sin(2^k pi t), cos(2^k pi t)] for k < 8


def time_embedding(t: float, batch: int, device: torch.device | str = "cpu") -> torch.Tensor:
    """[batch, 2 * TIME_FREQUENCIES] sinusoidal embedding of the flow time t in [0, 1)."""
    angles = t * math.pi * 2.0 ** torch.arange(TIME_FREQUENCIES, dtype=torch.float32, device=device)
    return torch.cat([angles.sin(), angles.cos()]).expand(batch, -1)


class FlowPolicy(ChunkPolicy):
    """pi(a_{t:t+K} | o_t, x_0): N Euler steps of a velocity field, the last one Gaussian."""

    kind = "flow"
    backbones = ("conv", "transformer")  # policy.backbone: the observation encoder

    def __init__(self, layout: ObsLayout, action_dim: int, chunk: int, hidden: list[int], channels: list[int],
                 embed_dim: int, denoise_steps: int, init_log_std: float = -0.5, encoder: nn.Module | None = None):
        """``encoder``: the observation backbone (``out_dim`` wide); default the conv ``ObsEncoder``."""
        super().__init__()
        if denoise_steps < 1:
            raise ValueError(f"policy.denoise_steps = {denoise_steps}: must be >= 1")
        self.layout, self.action_dim, self.chunk = layout, action_dim, chunk
        self.denoise_steps = denoise_steps  # N: not a parameter, may change between runs
        self.latent_shape = (chunk, action_dim)
        n = chunk * action_dim
        self.encoder = encoder if encoder is not None else ObsEncoder(layout, channels, embed_dim)
        self.velocity = mlp(n + 2 * TIME_FREQUENCIES + self.encoder.out_dim, hidden, n, 0.01)
        self.critic = mlp(self.encoder.out_dim, hidden, 1, 1.0)
        self.log_std = nn.Parameter(torch.full((n,), float(init_log_std)))

    @classmethod
    def from_config(cls, cfg: Any, layout: ObsLayout, action_dim: int, bounds: Any) -> "FlowPolicy":
        """``policy.backbone``: the conv ``ObsEncoder`` or the ``TransformerEncoder`` (width, depth, heads,
        patch)."""
        encoder = None
        if cfg.backbone == "transformer":
            encoder = TransformerEncoder(layout, cfg.width, cfg.depth, cfg.heads, cfg.patch)
        return cls(layout, action_dim, cfg.chunk, list(cfg.hidden), list(cfg.channels), cfg.embed_dim,
                   cfg.denoise_steps, cfg.init_log_std, encoder=encoder)

    @classmethod
    def latent_shape_of(cls, cfg: Any, action_dim: int) -> tuple[int, ...]:
        """x_0: one value per action of the chunk, [K, A]."""
        return (cfg.chunk, action_dim)

    def mean(self, features: torch.Tensor, x0: torch.Tensor) -> torch.Tensor:
        """mu(o, x_0): N Euler steps from the flat noise x0 [B, K*A]; differentiable."""
        x, steps, batch = x0, self.denoise_steps, x0.shape[0]
        for i in range(steps):
            x = x + self.velocity(torch.cat([x, time_embedding(i / steps, batch, x.device), features], 1)) / steps
        return x

    def dist(self, features: torch.Tensor, x0: torch.Tensor) -> Normal:
        mu = self.mean(features, x0)
        return Normal(mu, self.log_std.expand_as(mu).exp(), validate_args=False)  # see PolicyBase.heads

    def sample(self, obs: np.ndarray | torch.Tensor) -> tuple[torch.Tensor, ...]:
        features = self.encoder(self.flat(obs))
        batch = features.shape[0]
        x0 = torch.randn(batch, self.chunk * self.action_dim, device=features.device)
        d = self.dist(features, x0)
        a = d.rsample()  # loc + scale * eps: capturable (sample() checks scale >= 0 on the host)
        shape = (batch, self.chunk, self.action_dim)
        return a.reshape(shape), d.log_prob(a).sum(-1), self.critic(features).squeeze(-1), x0.reshape(shape)

    @torch.no_grad()
    def predict_chunk(self, obs: np.ndarray, deterministic: bool = True,
                      generator: torch.Generator | None = None) -> np.ndarray:
        """Deterministic: mu(o, x_0) from the fixed initial noise x_0 = 0 (the mode of the noise prior) and no
        noise at the final step; else x_0 ~ N(0, I) and a ~ N(mu, sigma^2), as in ``act``."""
        features = self.encoder(self.flat(obs))
        batch, n = features.shape[0], self.chunk * self.action_dim
        if deterministic:
            a = self.mean(features, torch.zeros(batch, n, device=features.device))
        else:
            mu = self.mean(features, noise((batch, n), generator, features.device))
            a = mu + self.log_std.exp() * noise(mu.shape, generator, mu.device)
        return a.reshape(batch, self.chunk, self.action_dim).float().cpu().numpy()

    def evaluate(self, obs: torch.Tensor, actions: torch.Tensor, latents: torch.Tensor) -> Tensors3:
        features = self.encoder(self.flat(obs))
        batch = features.shape[0]
        if tuple(latents.shape[1:]) != self.latent_shape:
            raise ValueError(f"flow policy latents must be [B, {self.chunk}, {self.action_dim}] (the x_0 act "
                             f"returned), got {list(latents.shape)}")
        d = self.dist(features, latents.reshape(batch, -1))
        return d.log_prob(actions.reshape(batch, -1)).sum(-1), d.entropy().sum(-1), self.critic(features).squeeze(-1)

    def value(self, obs: torch.Tensor) -> torch.Tensor:
        return self.critic(self.encoder(self.flat(obs))).squeeze(-1)
