"""Policy models behind one interface: ``act`` for generation, ``evaluate`` and ``value`` for training.

Four kinds (``policy.kind``): ``mlp`` (Gaussian chunk from the flat observation),
``cnn`` (conv image encoder + proprioception + instruction embedding, Gaussian
chunk), ``flow`` (flow-matching action head, the chunk by N denoising steps) and
``squashed`` (tanh-squashed Gaussian within the action bounds, SAC's actor).
The interface is :class:`ebrl.policies.base.ChunkPolicy`.
"""

from __future__ import annotations

from typing import Any

import numpy as np

from ebrl.envs.obs import ObsLayout
from ebrl.policies.base import ChunkPolicy
from ebrl.policies.checkpoint import load_arrays, load_checkpoint, save_checkpoint, state_arrays
from ebrl.policies.cnn import ChunkGaussianCNN
from ebrl.policies.flow import FlowPolicy
from ebrl.policies.mlp import ChunkGaussianMLP
from ebrl.policies.nets import ObsNormalizer
from ebrl.policies.squashed import ChunkSquashedMLP
from ebrl.policies.transformer import TransformerEncoder


def make_policy(policy_cfg: Any, layout: ObsLayout, action_dim: int,
                bounds: tuple[np.ndarray, np.ndarray] | None = None) -> ChunkPolicy:
    """The policy ``policy_cfg`` (a PolicySection) describes, for observations of ``layout`` and actions within
    ``bounds`` (low, high: the env's action space, which the ``squashed`` kind needs); loads
    ``policy_cfg.checkpoint`` (a path, resolved by the caller) when it is set."""
    cfg = policy_cfg
    if cfg.kind == "mlp":
        model: ChunkPolicy = ChunkGaussianMLP(layout, action_dim, cfg.chunk, list(cfg.hidden), cfg.init_log_std)
    elif cfg.kind == "cnn":
        model = ChunkGaussianCNN(layout, action_dim, cfg.chunk, list(cfg.hidden), list(cfg.channels), cfg.embed_dim,
                                 cfg.init_log_std)
    elif cfg.kind == "flow":
        encoder = None
        if getattr(cfg, "backbone", "conv") == "transformer":
            encoder = TransformerEncoder(layout, cfg.width, cfg.depth, cfg.heads, cfg.patch)
        model = FlowPolicy(layout, action_dim, cfg.chunk, list(cfg.hidden), list(cfg.channels), cfg.embed_dim,
                           cfg.denoise_steps, cfg.init_log_std, encoder=encoder)
    elif cfg.kind == "squashed":
        if bounds is None:
            raise ValueError("policy.kind = 'squashed' needs the env's action bounds")
        model = ChunkSquashedMLP(layout, action_dim, cfg.chunk, list(cfg.hidden), *bounds)
    else:
        raise ValueError(f"policy.kind = {cfg.kind!r} is not available (mlp, cnn, flow, squashed)")
    if cfg.normalize_obs:
        model.obs_norm = ObsNormalizer(layout)
    if cfg.checkpoint:
        load_checkpoint(model, cfg.checkpoint)
    return model


__all__ = ["ChunkGaussianCNN", "ChunkGaussianMLP", "ChunkPolicy", "ChunkSquashedMLP",
           "FlowPolicy", "load_arrays", "load_checkpoint", "ObsNormalizer", "make_policy", "save_checkpoint",
           "state_arrays"]
