"""What an environment returns is checked before anything learns from it (the bus's messages are checked the same
way on arrival, ``ebrl.messages``): a reward that is not finite counts as 0, one beyond ``env.max_abs_reward`` (per
env step) is clipped to it, and an observation that is not finite ends its episode there (as a truncation, its
non-finite entries read as 0). Each is counted in the sim stats (``sim/rewards_nonfinite``,
``sim/rewards_clipped``, ``sim/obs_nonfinite``): a buggy env costs a few bad steps, never a poisoned policy."""

from __future__ import annotations

import math
from dataclasses import dataclass

import numpy as np


@dataclass
class Guarded:
    """What a chunk's checks found, per env: how many rewards were clipped or not finite, and observations not
    finite."""

    rewards_clipped: int = 0
    rewards_nonfinite: int = 0
    obs_nonfinite: int = 0

    def __bool__(self) -> bool:
        return bool(self.rewards_clipped or self.rewards_nonfinite or self.obs_nonfinite)


def reward(value: float, bound: float, seen: Guarded) -> float:
    """One env step's reward as training may see it (``seen`` counts what was changed)."""
    value = float(value)
    if not math.isfinite(value):
        seen.rewards_nonfinite += 1
        return 0.0
    if abs(value) > bound:
        seen.rewards_clipped += 1
        return math.copysign(bound, value)
    return value


def observation(obs: np.ndarray, seen: Guarded) -> tuple[np.ndarray, bool]:
    """An observation with its non-finite entries as 0, and whether it had any (its episode then ends)."""
    if obs.dtype.kind != "f" or np.isfinite(obs).all():
        return obs, False
    seen.obs_nonfinite += 1
    return np.nan_to_num(obs, nan=0.0, posinf=0.0, neginf=0.0), True


def rewards(values, bound: float):
    """A batch's rewards of one env step (a torch tensor [N]) as training may see them: (rewards, clipped [N] bool,
    not finite [N] bool)."""
    import torch

    nonfinite = ~torch.isfinite(values)
    values = torch.where(nonfinite, torch.zeros_like(values), values)
    clipped = values.abs() > bound
    return values.clamp(-bound, bound), clipped, nonfinite


def observations(values):
    """A batch's observations of one env step (a torch tensor [N, ...]) with non-finite entries as 0, and which
    envs had any ([N] bool: their episodes end)."""
    import torch

    broken = ~torch.isfinite(values.reshape(len(values), -1)).all(dim=1)
    return torch.nan_to_num(values, nan=0.0, posinf=0.0, neginf=0.0), broken


def decision_bound(bound: float, steps: np.ndarray) -> np.ndarray:
    """The largest reward a decision of ``steps`` env steps can carry from a sim that clips at ``bound``."""
    return bound * np.maximum(steps, 1) * (1 + 1e-6)
