"""Policy models behind one interface: ``act`` for generation, ``evaluate`` and ``value`` for training.

``policy.kind`` names a kind of :mod:`ebrl.policies.registry`: ``mlp`` (Gaussian chunk from the flat observation),
``cnn`` (conv image encoder + proprioception + instruction embedding, Gaussian chunk), ``flow`` (flow-matching
action head, the chunk by N denoising steps), ``squashed`` (tanh-squashed Gaussian within the action bounds,
SAC's actor), ``vla`` (a vision-language-action model, ``ebrl.policies.vla``), or a user's own
:class:`~ebrl.policies.base.ChunkPolicy` subclass as ``"pkg.module:MyPolicy"`` (docs/policies.md).

The package imports no policy, nor torch, until one is used (the config checks ``policy.kind`` against the
registry in every process, the simulator's among them): its names load on first use.
"""

from __future__ import annotations

from typing import TYPE_CHECKING, Any

from ebrl.policies.registry import canonical, policy_class

if TYPE_CHECKING:
    import numpy as np

    from ebrl.envs.obs import ObsLayout
    from ebrl.policies.base import ChunkPolicy

_LAZY = {
    "ChunkPolicy": "ebrl.policies.base",
    "GaussianChunkPolicy": "ebrl.policies.base",
    "ChunkGaussianMLP": "ebrl.policies.mlp",
    "ChunkGaussianCNN": "ebrl.policies.cnn",
    "FlowPolicy": "ebrl.policies.flow",
    "ChunkSquashedMLP": "ebrl.policies.squashed",
    "ObsNormalizer": "ebrl.policies.nets",
    "load_arrays": "ebrl.policies.checkpoint",
    "load_checkpoint": "ebrl.policies.checkpoint",
    "save_checkpoint": "ebrl.policies.checkpoint",
    "state_arrays": "ebrl.policies.checkpoint",
}


def make_policy(policy_cfg: Any, layout: ObsLayout, action_dim: int,
                bounds: tuple[np.ndarray, np.ndarray] | None = None) -> ChunkPolicy:
    """The policy ``policy_cfg`` (a PolicySection) describes, for observations of ``layout`` and actions within
    ``bounds`` (low, high: the env's action space, which a kind with ``needs_bounds`` needs): its kind's class
    (:func:`~ebrl.policies.registry.policy_class`) builds it (``from_config``); then the steps every kind shares:
    the observation normaliser (``policy.normalize_obs``) and ``policy.checkpoint`` (a path, resolved by the
    caller) when it is set."""
    from ebrl.policies.checkpoint import load_checkpoint
    from ebrl.policies.nets import ObsNormalizer

    cfg = policy_cfg
    cls = policy_class(cfg.kind)
    if cls.needs_bounds and bounds is None:
        raise ValueError(f"policy.kind = {cfg.kind!r} needs the env's action bounds")
    if cfg.backbone not in cls.backbones:
        raise ValueError(f"policy.backbone = {cfg.backbone!r}: policy.kind = {cfg.kind!r} reads "
                         f"{' or '.join(map(repr, cls.backbones))}")
    model = cls.from_config(cfg, layout, action_dim, bounds)
    expected = tuple(cls.latent_shape_of(cfg, action_dim))
    if tuple(model.latent_shape) != expected:  # the simulator sizes its messages by latent_shape_of
        raise ValueError(f"policy.kind = {cfg.kind!r}: the model's latent_shape {tuple(model.latent_shape)} is not "
                         f"what its class's latent_shape_of says, {expected}")
    model.kind = canonical(cfg.kind)
    if model.options is None:
        model.options = dict(cfg.options)
    if cfg.normalize_obs:
        model.obs_norm = ObsNormalizer(layout)
    if cfg.checkpoint:
        load_checkpoint(model, cfg.checkpoint)
    return model


def __getattr__(name: str) -> Any:
    if name in _LAZY:
        import importlib

        return getattr(importlib.import_module(_LAZY[name]), name)
    raise AttributeError(f"module 'ebrl.policies' has no attribute {name!r}")


__all__ = ["make_policy", "policy_class", *_LAZY]
