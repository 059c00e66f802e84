"""A user's own algorithm, as a user writes one outside EBRL (``algo.name = "user_algos:VanillaPG"``): REINFORCE
with a learned value baseline over the policy's chunks, built only on the public interface
(``ebrl.algos.algorithm``) and the on-policy collector."""

from __future__ import annotations

from typing import Any, Callable

import numpy as np
import torch

from ebrl.algos.algorithm import Algorithm, Learned
from ebrl.algos.ppo import SegmentCollector


class VanillaPG(Algorithm):
    """One gradient step per update: -log pi(a|s) * (G - V(s)) + (G - V(s))^2 / 2, G the discounted return-to-go
    within each segment (bootstrapped from the value of its last observation)."""

    name = "vanilla-pg"

    def __init__(self, model: Any, cfg: Any, info: Any, telemetry: Any, device: torch.device):
        super().__init__(model, cfg, info, telemetry, device)
        self.adam = torch.optim.Adam(model.parameters(), lr=cfg.train.lr)

    def collector(self, max_pending: int, max_staleness: int, count: Callable[[str, float], None]) -> Any:
        return SegmentCollector(self.cfg.algo, max_pending, max_staleness, count)

    @property
    def optimizer(self) -> torch.optim.Optimizer:
        return self.adam

    def learn(self, items: list, version: int, collector: Any) -> Learned:
        gamma = self.cfg.algo.gamma
        obs, actions, latents, returns = [], [], [], []
        for seg in items:
            with torch.no_grad():
                g = 0.0 if seg.end == "terminated" else float(self.model.value(torch.from_numpy(seg.last_obs[None]))[0])
            out = np.zeros(len(seg.rewards), np.float32)
            for t in reversed(range(len(seg.rewards))):
                g = float(seg.rewards[t]) + gamma ** int(seg.steps[t]) * g
                out[t] = g
            obs.append(seg.obs), actions.append(seg.actions), latents.append(seg.latents), returns.append(out)
        o, a, z = (torch.from_numpy(np.concatenate(x)) for x in (obs, actions, latents))
        g = torch.from_numpy(np.concatenate(returns))
        logp, _, value = self.model.evaluate(o, a, z)
        adv = (g - value).detach()
        loss = -(logp * (adv - adv.mean()) / (adv.std() + 1e-8)).mean() + 0.5 * (g - value).square().mean()
        self.adam.zero_grad()
        loss.backward()
        if not torch.isfinite(loss):
            self.adam.zero_grad()
            return Learned({"steps_skipped": 1.0}, np.concatenate([s.versions for s in items]))
        self.adam.step()
        return Learned({"vpg_loss": float(loss), "batch_size": float(len(g))},
                       np.concatenate([s.versions for s in items]))
