"""A tanh-squashed Gaussian chunk policy within the action bounds: SAC's actor (Haarnoja et al. 2018, appendix C;
as Stable-Baselines3's ``SquashedDiagGaussianDistribution``).

u ~ N(mu(o), sigma(o)) over the chunk's K x A values, a = tanh(u) in (-1, 1), and the env's action is
``low + (a + 1) / 2 * (high - low)``. The log-prob is of ``a``, the squashed one:

    log pi(a | o) = sum_i [ log N(u_i; mu_i, sigma_i) - log(1 - tanh(u_i)^2 + 1e-6) ]

(an affine map to the bounds shifts every log-prob by the same constant, which SAC's entropy target absorbs: it is
not added). The bounds are buffers of the model, so they travel with its weights and checkpoints; ``value`` is
zero (SAC learns Q functions beside the policy, ``ebrl.algos.sac``, not a value head).
"""

from __future__ import annotations

import math
from typing import Any

import numpy as np
import torch
from torch import nn

from ebrl.envs.obs import ObsLayout
from ebrl.policies.base import HALF_LOG_2PI, ChunkPolicy, Tensors3, noise
from ebrl.policies.nets import layer, mlp, width

LOG_STD_MIN, LOG_STD_MAX = -20.0, 2.0  # Stable-Baselines3's and the SAC authors' clamp
TANH_EPS = 1e-6


def relu_mlp(n_in: int, hidden: list[int], n_out: int | None) -> nn.Sequential:
    """ReLU MLP (SAC's actors and critics, as Stable-Baselines3's); ``n_out=None`` ends after the last hidden
    layer."""
    return mlp(n_in, hidden, n_out, 0.01, nn.ReLU)


class ChunkSquashedMLP(ChunkPolicy):
    """pi(a_{t:t+K} | o_t): tanh of a diagonal Gaussian with state-dependent log-std, scaled to the bounds."""

    kind = "squashed"
    latent_shape = (0,)
    needs_bounds = True
    trained_by = frozenset({"sac"})  # no value head: ppo and grpo refuse it; sac calls rsample_flat, to_env, warmup

    def __init__(self, layout: ObsLayout, action_dim: int, chunk: int, hidden: list[int],
                 low: np.ndarray, high: np.ndarray):
        super().__init__()
        low, high = np.broadcast_to(np.asarray(low, np.float64), (action_dim,)), \
            np.broadcast_to(np.asarray(high, np.float64), (action_dim,))
        if not (np.isfinite(low).all() and np.isfinite(high).all() and (high > low).all()):
            raise ValueError(f"policy.kind = 'squashed' needs finite action bounds with low < high; the env's are "
                             f"low={low.tolist()}, high={high.tolist()}")
        self.layout, self.obs_dim, self.action_dim, self.chunk = layout, layout.size, action_dim, chunk
        n = chunk * action_dim
        self.trunk = relu_mlp(self.obs_dim, list(hidden), None)
        self.mean = layer(width(self.obs_dim, list(hidden)), n, 0.01)
        self.log_std = layer(width(self.obs_dim, list(hidden)), n, 0.01)
        # the chunk's bounds, flat over K x A: mid + half * tanh(u)
        self.register_buffer("action_mid", torch.as_tensor(np.tile((high + low) / 2, chunk), dtype=torch.float32))
        self.register_buffer("action_half", torch.as_tensor(np.tile((high - low) / 2, chunk), dtype=torch.float32))
        # 1: sample() acts uniformly within the bounds (SAC's warm-up before its first gradient step, as
        # Stable-Baselines3's); a buffer, so that generation acts as the weights it holds say
        self.register_buffer("warmup", torch.zeros(()))

    @classmethod
    def from_config(cls, cfg: Any, layout: ObsLayout, action_dim: int,
                    bounds: tuple[np.ndarray, np.ndarray] | None) -> "ChunkSquashedMLP":
        if bounds is None:
            raise ValueError(f"policy.kind = {cfg.kind!r} needs the env's action bounds")
        return cls(layout, action_dim, cfg.chunk, list(cfg.hidden), *bounds)

    def moments(self, flat_obs: torch.Tensor) -> tuple[torch.Tensor, torch.Tensor]:
        """mu and log sigma of u, [B, K*A] each, from standardised flat observations; in float32 also under
        bfloat16 autocast (``policy.dtype``): tanh rounds to exactly 1 in bfloat16's 8 bits, and the squash's
        log(1 - tanh^2 + 1e-6) would then be -inf."""
        h = self.trunk(flat_obs)
        return self.mean(h).float(), self.log_std(h).float().clamp(LOG_STD_MIN, LOG_STD_MAX)

    def rsample(self, obs: torch.Tensor) -> tuple[torch.Tensor, torch.Tensor]:
        """Reparameterised: squashed actions in (-1, 1) [B, K*A] (gradients flow through them) and their log-probs
        [B]."""
        return self.rsample_flat(self.flat(obs))

    def rsample_flat(self, flat_obs: torch.Tensor) -> tuple[torch.Tensor, torch.Tensor]:
        """:meth:`rsample` of observations already flat and standardised (SAC standardises a batch once)."""
        mean, log_std = self.moments(flat_obs)
        eps = torch.randn_like(mean)
        u = mean + log_std.exp() * eps
        a = torch.tanh(u)
        logp = (-0.5 * eps.square() - log_std - HALF_LOG_2PI - torch.log1p(-a.square() + TANH_EPS)).sum(-1)
        return a, logp

    def to_env(self, squashed: torch.Tensor) -> torch.Tensor:
        """Squashed actions [B, K*A] in (-1, 1) as the env's chunks [B, K, A] within its bounds."""
        a = self.action_mid + self.action_half * squashed
        return a.reshape(a.shape[0], self.chunk, self.action_dim)

    def from_env(self, actions: torch.Tensor) -> torch.Tensor:
        """The env's chunks [B, K, A] as squashed values [B, K*A] in [-1, 1] (what the critics take)."""
        return ((actions.reshape(actions.shape[0], -1) - self.action_mid) / self.action_half).clamp(-1.0, 1.0)

    def sample(self, obs: np.ndarray | torch.Tensor) -> tuple[torch.Tensor, ...]:
        """Chunks to act with, their log-probs, zero values and no latents; in the warm-up, uniform chunks (their
        log-prob: the uniform density's in the squashed scale, -log 2 per value)."""
        a, logp = self.rsample(obs)
        on = self.warmup > 0  # on the device, no read back (generation may replay this as a CUDA graph)
        a = torch.where(on, torch.rand_like(a) * 2 - 1, a)
        logp = torch.where(on, torch.full_like(logp, -math.log(2.0) * a.shape[-1]), logp)
        return self.to_env(a), logp, logp.new_zeros(a.shape[0]), a.new_zeros(a.shape[0], 0)

    def evaluate(self, obs: torch.Tensor, actions: torch.Tensor, latents: torch.Tensor) -> Tensors3:
        """Log-prob of given chunks (inverting the squash), an entropy estimate (minus the log-prob of a fresh
        sample) and zero values: for completeness of the interface; SAC's updates use :meth:`rsample`."""
        mean, log_std = self.moments(self.flat(obs))
        a = self.from_env(actions).clamp(-1 + TANH_EPS, 1 - TANH_EPS)
        u = torch.atanh(a)
        z = (u - mean) / log_std.exp()
        logp = (-0.5 * z.square() - log_std - HALF_LOG_2PI - torch.log1p(-a.square() + TANH_EPS)).sum(-1)
        _, fresh = self.rsample(obs)
        return logp, -fresh, torch.zeros_like(logp)

    def value(self, obs: torch.Tensor) -> torch.Tensor:
        return torch.zeros(obs.shape[0], device=self.device)

    @torch.no_grad()
    def predict_chunk(self, obs: np.ndarray, deterministic: bool = True,
                      generator: torch.Generator | None = None) -> np.ndarray:
        """Deterministic: tanh of the mean, scaled (SAC's evaluation action); else a sample from ``generator``."""
        mean, log_std = self.moments(self.flat(obs))
        u = mean if deterministic else mean + log_std.exp() * noise(mean.shape, generator, mean.device)
        return self.to_env(torch.tanh(u)).float().cpu().numpy()
