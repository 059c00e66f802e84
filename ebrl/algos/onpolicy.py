"""PPO and GRPO behind the algorithm interface (``ebrl.algos.algorithm``): on-policy segments in, PPO's update.

PPO's collector hands each update the oldest ``train.batch_size`` decisions, stale prefixes cut
(``ebrl.algos.ppo.SegmentCollector``); GRPO's hands whole episodes of groups from the same initial state
(``ebrl.algos.grpo.GroupCollector``). Both then run decoupled PPO's update (``ebrl.algos.ppo.PPO``): the proximal
policy's log-probs before the observation normaliser takes in the batch, then ``epochs`` x ``minibatches``
gradient steps. Both train data-parallel: every rank makes the same collective calls in the same order, data
or not (a rank without data steps with zero gradients).
"""

from __future__ import annotations

import contextlib
from typing import Any, Callable

import numpy as np
import torch

from ebrl import devices
from ebrl.algos.algorithm import Algorithm, Learned
from ebrl.algos.grpo import GroupCollector
from ebrl.algos.ppo import PPO, BadBatch, Batch, SegmentCollector
from ebrl.policies.registry import trained_by_problem


class PPOAlgorithm(Algorithm):
    """Decoupled PPO with GAE and a critic (the policy's value head)."""

    name = "ppo"
    data_parallel = True
    collector_class: Any = SegmentCollector

    def __init__(self, model: Any, cfg: Any, info: Any, telemetry: Any, device: torch.device):
        super().__init__(model, cfg, info, telemetry, device)
        if problem := trained_by_problem(model, self.name):  # e.g. squashed: SAC's actor, no value head
            raise ValueError(problem)
        self.ppo = PPO(model, cfg.algo, cfg.train.lr, seed=cfg.run.seed)
        self.dp: Any = None

    def collector(self, max_pending: int, max_staleness: int, count: Callable[[str, float], None]) -> Any:
        return self.collector_class(self.cfg.algo, max_pending, max_staleness, count)

    def join(self, dp: Any) -> None:
        """Several ranks: the gradient steps go through the training group's wrapped policy and optimizer."""
        self.dp = dp
        self.ppo.net, self.ppo.optimizer = dp.net, dp.optimizer

    def prepare(self) -> None:
        self.ppo.prepare()

    @property
    def optimizer(self) -> torch.optim.Optimizer:
        return self.ppo.optimizer

    def generators(self) -> dict[str, torch.Generator]:
        return {"ppo": self.ppo.generator}

    def learn(self, items: list, version: int, collector: Any) -> Learned:
        """The gradient steps on ``items``; a rank without items steps with zero gradients."""
        with self.dp.gathered() if self.dp is not None else contextlib.nullcontext():
            batch = checked_batch(collector, items, self.model, self.telemetry)
        batch = batch.to(self.device) if batch is not None else None
        dtype = self.cfg.policy.dtype
        prox = None  # log pi_prox: the policy as it acted, before the normaliser takes in this batch
        if batch is not None:
            with devices.autocast(self.device, dtype):
                prox = self.ppo.proximal(batch)
        if self.model.obs_norm is not None:  # before the gradient steps, the same statistics on every rank
            obs = batch.obs if batch is not None else torch.zeros(0, *self.info.obs_shape)
            sums = self.model.obs_norm.sums(obs)
            self.model.obs_norm.merge(sums if self.dp is None else self.dp.all_sum(sums))
        if batch is None:
            with devices.autocast(self.device, dtype):
                return Learned({**self.ppo.update(self.empty_batch(version), scale=0.0), "batch_size": 0.0})
        staleness = version - batch.versions
        with devices.autocast(self.device, dtype):
            out = self.ppo.update(batch, version=version, prox=prox)
        out.update(staleness_mean=float(staleness.mean()), staleness_max=float(staleness.max()),
                   batch_size=float(len(batch)))
        return Learned(out, batch.versions)

    def empty_batch(self, version: int) -> Batch:
        """Zeros shaped like a batch of ``algo.minibatches`` decisions (for ``scale = 0`` steps)."""
        n, zeros = self.cfg.algo.minibatches, torch.zeros(self.cfg.algo.minibatches)
        return Batch(obs=torch.zeros(n, *self.info.obs_shape),
                     actions=torch.zeros(n, self.cfg.policy.chunk, self.info.action_dim),
                     latents=torch.zeros(n, *self.model.latent_shape), logprobs=zeros, advantages=zeros, returns=zeros,
                     values=zeros, versions=np.full(n, version)).to(self.device)


class GRPOAlgorithm(PPOAlgorithm):
    """Group-relative advantages over ``algo.group_size`` rollouts from the same initial state, no critic."""

    name = "grpo"
    collector_class = GroupCollector


def checked_batch(collector: Any, items: list, model: torch.nn.Module, telemetry: Any) -> Batch | None:
    """The batch of ``items`` (None for none), without the decisions whose advantages or returns are not finite
    (counted: ``train/decisions_dropped``; None when that is all of them)."""
    if not items:
        return None
    try:
        batch = collector.build(items, model)
    except BadBatch as exc:
        telemetry.count("train/decisions_dropped", exc.dropped)
        return None
    if batch.dropped:
        telemetry.count("train/decisions_dropped", batch.dropped)
    return batch
