"""Policy models behind one interface: ``act`` for generation, ``evaluate`` for training."""

from __future__ import annotations

from typing import Any

import numpy as np
import torch

from ebrl.envs.obs import ObsLayout
from ebrl.policies.mlp import ChunkGaussianMLP


def make_policy(policy_cfg: Any, layout: ObsLayout, action_dim: int) -> ChunkGaussianMLP:
    if policy_cfg.kind == "mlp":
        return ChunkGaussianMLP(layout.size, action_dim, policy_cfg.chunk, list(policy_cfg.hidden),
                                policy_cfg.init_log_std)
    raise ValueError(f"policy.kind = {policy_cfg.kind!r} is not available")


def state_arrays(model: torch.nn.Module) -> dict[str, np.ndarray]:
    """The model's state dict as numpy arrays (what the Weights message carries)."""
    return {name: t.detach().cpu().numpy().copy() for name, t in model.state_dict().items()}


def load_arrays(model: torch.nn.Module, params: dict[str, np.ndarray]) -> None:
    """Load arrays from a Weights message; raise ValueError if names or shapes do not match."""
    state = model.state_dict()
    if set(params) != set(state):
        raise ValueError(f"weights do not match the model: missing {sorted(set(state) - set(params))}, "
                         f"unexpected {sorted(set(params) - set(state))}")
    with torch.no_grad():
        for name, tensor in state.items():
            value = params[name]
            if tuple(value.shape) != tuple(tensor.shape):
                raise ValueError(f"weights {name}: shape {value.shape}, model has {tuple(tensor.shape)}")
            tensor.copy_(torch.from_numpy(np.array(value)))


__all__ = ["ChunkGaussianMLP", "load_arrays", "make_policy", "state_arrays"]
