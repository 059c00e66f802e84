"""The policy interface every kind implements: ``act`` for generation, ``evaluate`` and ``value`` for training.

A policy maps one flat float32 observation per env (``[B, layout.size]``, or
``[B, *obs_shape]`` of the same size) to a chunk of K actions. ``act`` samples
and also returns the *latents*: whatever randomness, beyond the actions
themselves, training needs to recompute the exact log-prob of the chunk
(``[B, *latent_shape]``; empty for a Gaussian policy, the initial noise x0 of a
flow policy). The training service stores them beside the actions and passes
them back to ``evaluate``.
"""

from __future__ import annotations

import math
from typing import Any, ClassVar

import numpy as np
import torch
from torch import nn
from torch.distributions import Normal

from ebrl.envs.obs import ObsLayout
from ebrl.policies.nets import ObsNormalizer

Tensors3 = tuple[torch.Tensor, torch.Tensor, torch.Tensor]
HALF_LOG_2PI = 0.5 * math.log(2 * math.pi)


class ChunkPolicy(nn.Module):
    """pi(a_{t:t+K} | o_t, z): what the generation and training services call.

    A kind (``policy.kind``, ``ebrl.policies.registry``) is a subclass that builds itself from the ``[policy]``
    section (:meth:`from_config`) and says, as class attributes, what other modules need to know of it without
    building one: its latents (:meth:`latent_shape_of`), whether it needs the env's action bounds, the algorithms
    that can train it, the ``policy.backbone`` values it reads and whether its :meth:`sample` can be captured as
    a CUDA graph. docs/policies.md is the user's guide.
    """

    kind: str  # policy.kind of the config (set by make_policy); stored in checkpoints
    layout: ObsLayout
    chunk: int  # K
    action_dim: int  # A
    latent_shape: tuple[int, ...]
    # what a checkpoint stores as policy.options to rebuild this model from the checkpoint alone; None: the
    # config's policy.options as given (make_policy sets them)
    options: dict[str, Any] | None = None

    needs_bounds: ClassVar[bool] = False  # from_config needs the env's action bounds (low, high)
    trained_by: ClassVar[frozenset[str]] = frozenset({"ppo", "grpo"})  # the registered algorithms that train it
    backbones: ClassVar[tuple[str, ...]] = ("conv",)  # the policy.backbone values it reads ("conv": the default)
    capturable: ClassVar[bool] = True  # gen.compile may capture sample() as a CUDA graph (ebrl.policies.graphs)

    def __init__(self) -> None:
        super().__init__()
        self.obs_norm: ObsNormalizer | None = None  # policy.normalize_obs: set by make_policy

    @classmethod
    def from_config(cls, cfg: Any, layout: ObsLayout, action_dim: int,
                    bounds: tuple[np.ndarray, np.ndarray] | None) -> "ChunkPolicy":
        """The policy ``cfg`` (the PolicySection; kind-specific options in ``cfg.options``) describes, for
        observations of ``layout``, actions of ``action_dim`` values and, where the env's action space has them,
        its ``bounds`` (low, high; None where the caller has none: a kind with ``needs_bounds`` always gets
        them). Fresh weights: ``make_policy`` adds the observation normaliser and loads a checkpoint after."""
        raise NotImplementedError(f"{cls.__module__}.{cls.__qualname__} does not say how to build it from a config: "
                                  "define the classmethod from_config(cls, cfg, layout, action_dim, bounds)")

    @classmethod
    def latent_shape_of(cls, cfg: Any, action_dim: int) -> tuple[int, ...]:
        """The ``latent_shape`` of the policy :meth:`from_config` builds from ``cfg``, known without building it
        (the simulator's message bounds): by default the class's own ``latent_shape``."""
        shape = getattr(cls, "latent_shape", None)
        if shape is None:
            raise NotImplementedError(f"{cls.__module__}.{cls.__qualname__}: set the class attribute latent_shape "
                                      "or define the classmethod latent_shape_of(cls, cfg, action_dim)")
        return tuple(shape)

    @torch.no_grad()
    def act(self, obs: np.ndarray | torch.Tensor) -> tuple[np.ndarray, np.ndarray, np.ndarray, np.ndarray]:
        """Sample chunks (no gradients): actions [B, K, A], log-probs [B], values [B], latents [B, *latent_shape],
        float32 numpy arrays, read back from the device in one transfer."""
        return to_host(*self.sample(obs))

    def sample(self, obs: np.ndarray | torch.Tensor) -> tuple[torch.Tensor, ...]:
        """What ``act`` returns, as tensors on the policy's device (call under ``torch.no_grad``): the part of a
        forward pass with fixed shapes for a batch size, which ``ebrl.policies.graphs`` captures as a CUDA graph."""
        raise NotImplementedError

    def evaluate(self, obs: torch.Tensor, actions: torch.Tensor, latents: torch.Tensor) -> Tensors3:
        """Log-prob of the given chunks, entropy and value, all [B], with gradients (training)."""
        raise NotImplementedError

    def value(self, obs: torch.Tensor) -> torch.Tensor:
        """V(o_t), [B]."""
        raise NotImplementedError

    def predict_chunk(self, obs: np.ndarray, deterministic: bool = True,
                      generator: torch.Generator | None = None) -> np.ndarray:
        """Chunks for acting outside training (evaluation, a deployed policy): actions [B, K, A], float32.
        ``deterministic``: the same observation always gives the same chunk (each kind says which); else a
        sample, drawn from ``generator`` (a CPU generator; default torch's global one)."""
        raise NotImplementedError

    @property
    def device(self) -> torch.device:
        return next(self.parameters()).device

    def flat(self, obs: torch.Tensor | np.ndarray) -> torch.Tensor:
        """Observations as a float32 tensor [B, layout.size] on the policy's device, standardised when the policy
        normalises them (every entry point, ``act``, ``evaluate`` and ``value``, passes them through here once)."""
        o = torch.as_tensor(obs, dtype=torch.float32, device=self.device)
        o = o.reshape(o.shape[0], self.layout.size)
        return o if self.obs_norm is None else self.obs_norm(o)


def to_host(*tensors: torch.Tensor) -> tuple[np.ndarray, ...]:
    """``tensors`` (same leading size B) as float32 numpy arrays, what ``act`` returns once per batch: from an
    accelerator in ONE device-to-host transfer; on the CPU the tensors' own memory (the concatenation and the
    copy cost 40 µs of a 110 µs forward pass of a small MLP)."""
    if all(t.device.type == "cpu" for t in tensors):  # nothing to transfer: no copy, no concatenation
        return tuple((t if t.dtype == torch.float32 else t.float()).numpy() for t in tensors)
    batch = tensors[0].shape[0]
    widths = [math.prod(t.shape[1:]) for t in tensors]  # explicit: a [B, 0] has no -1
    flat = torch.cat([t.reshape(batch, w).float() for t, w in zip(tensors, widths)], 1).cpu().numpy()
    out, col = [], 0
    for t, width in zip(tensors, widths):
        out.append(flat[:, col:col + width].reshape(t.shape))
        col += width
    return tuple(out)


class GaussianChunkPolicy(ChunkPolicy):
    """A diagonal Gaussian over the whole chunk (K x A means, learned log-std); no latents."""

    latent_shape = (0,)

    def moments(self, obs: torch.Tensor) -> tuple[torch.Tensor, torch.Tensor, torch.Tensor]:
        """From one pass over flat ``obs``: the chunk's flat K*A means [B, K*A], their log-stds (broadcastable
        to the means) and the value [B]."""
        raise NotImplementedError

    def heads(self, obs: torch.Tensor) -> tuple[Normal, torch.Tensor]:
        """The chunk distribution over flat K*A actions and the value, from one pass over ``obs``."""
        mean, log_std, v = self.moments(obs)
        # no argument checks: a non-finite mean makes a non-finite loss, which the update skips (ebrl.algos.ppo),
        # where a check would raise and end the process
        return Normal(mean, log_std.expand_as(mean).exp(), validate_args=False), v

    def sample(self, obs: np.ndarray | torch.Tensor) -> tuple[torch.Tensor, ...]:
        """mean + std * eps and its log-prob, written out rather than through ``torch.distributions.Normal``:
        generation's hot path, where building and checking a distribution cost more than the MLP itself
        (about 130 of 225 µs for a 64x64 MLP on 4 observations, one CPU thread). The same density as
        ``Normal(mean, std).log_prob`` (``evaluate``: ``tests/test_policies.py`` pins the two to agree); capturable as a CUDA graph
        (no read-back to the host)."""
        mean, log_std, v = self.moments(self.flat(obs))
        log_std = log_std.expand_as(mean)
        eps = torch.randn_like(mean)
        a = mean + log_std.exp() * eps
        logp = (-0.5 * eps.square() - log_std - HALF_LOG_2PI).sum(-1)
        batch = a.shape[0]
        return a.reshape(batch, self.chunk, self.action_dim), logp, v, a.new_zeros(batch, 0)

    def evaluate(self, obs: torch.Tensor, actions: torch.Tensor, latents: torch.Tensor) -> Tensors3:
        d, v = self.heads(self.flat(obs))
        flat = actions.reshape(actions.shape[0], -1)
        return d.log_prob(flat).sum(-1), d.entropy().sum(-1), v

    @torch.no_grad()
    def predict_chunk(self, obs: np.ndarray, deterministic: bool = True,
                      generator: torch.Generator | None = None) -> np.ndarray:
        """Deterministic: the Gaussian's mean; else mean + std * noise."""
        d, _ = self.heads(self.flat(obs))
        a = d.mean
        if not deterministic:
            a = a + d.stddev * noise(a.shape, generator, a.device)
        return a.reshape(a.shape[0], self.chunk, self.action_dim).float().cpu().numpy()


def noise(shape: torch.Size | tuple[int, ...], generator: torch.Generator | None, device: torch.device) -> torch.Tensor:
    """Standard normal noise drawn on the CPU from ``generator`` (reproducible whatever the device), moved to
    ``device``."""
    return torch.randn(tuple(shape), generator=generator).to(device)
