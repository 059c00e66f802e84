"""GRPO: group-relative advantages over rollouts from the same initial state, no critic
(Shao et al. 2024, "DeepSeekMath", section 4.1; outcome supervision).

The ``group_size`` environments ``g * group_size ... (g + 1) * group_size - 1``
reset with the same seeds (ebrl/services/sim.py), so their k-th episodes start from
the same initial state; actions are sampled independently, so the episodes
differ. When all ``group_size`` k-th episodes have finished, each episode's
advantage is its return standardised within the group,

    A_i = (R_i - mean(R)) / (std(R) + eps),

and every chunk decision of episode i gets A_i. The policy loss is PPO's
clipped (and, for stale data, decoupled) surrogate with these advantages; no
value loss is trained. Decisions more than ``max_staleness`` versions behind
the update are dropped from the batch (they still count in the return).
"""

from __future__ import annotations

import collections
import math
from dataclasses import dataclass
from typing import Any, Callable

import numpy as np
import torch
from torch import nn

from ebrl.algos.ppo import Batch
from ebrl.messages import MessageError, TrajectorySegment, from_wire, to_wire


def group_advantages(returns: np.ndarray, eps: float = 1e-6) -> np.ndarray:
    """Returns standardised within their group; a group whose returns are all equal carries no signal (zeros)."""
    returns = np.asarray(returns, dtype=np.float64)
    return ((returns - returns.mean()) / (returns.std() + eps)).astype(np.float32)


@dataclass
class Episode:
    """One finished episode of one environment: its segments in order."""

    env_id: int
    index: int
    segments: list[TrajectorySegment]

    @property
    def decisions(self) -> int:
        return sum(len(s.obs) for s in self.segments)

    @property
    def ret(self) -> float:
        return float(sum(s.rewards.sum() for s in self.segments))

    def cat(self, name: str) -> np.ndarray:
        return np.concatenate([getattr(s, name) for s in self.segments])


class GroupCollector:
    """GRPO's side of the train service: assembles each environment's segments into episodes and
    episodes into groups (same group, same episode index). Bounded: beyond ``max_pending`` buffered
    decisions the oldest unfinished group is dropped (counted); an episode whose segments arrive with
    a gap (a segment lost upstream) is dropped too, never trained on."""

    def __init__(self, algo_cfg: Any, max_pending: int, max_staleness: int, count: Callable[[str, float], None]):
        self.cfg, self.max_pending, self.max_staleness, self.count = algo_cfg, max_pending, max_staleness, count
        self.group_size = int(algo_cfg.group_size)
        self.open: dict[int, list[TrajectorySegment]] = {}  # env id -> segments of its current episode
        self.waiting: dict[tuple[int, int], dict[int, Episode]] = {}  # (group, episode index) -> finished episodes
        self.ready: collections.deque[list[Episode]] = collections.deque()
        self.pending_steps = 0  # every buffered decision
        self.ready_steps = 0  # decisions in complete groups

    def add(self, seg: TrajectorySegment) -> None:
        segs = self.open.get(seg.env_id)
        if segs and segs[-1].episode != seg.episode:  # the end of that episode never arrived
            self._drop_open(seg.env_id)
            segs = None
        self.open.setdefault(seg.env_id, []).append(seg)
        self.pending_steps += len(seg.obs)
        if seg.end != "cut":
            episode = Episode(seg.env_id, seg.episode, self.open.pop(seg.env_id))
            key = (seg.env_id // self.group_size, seg.episode)
            members = self.waiting.setdefault(key, {})
            members[seg.env_id] = episode
            if len(members) == self.group_size:
                group = list(self.waiting.pop(key).values())
                self.ready.append(group)
                self.ready_steps += sum(e.decisions for e in group)
                self.count("train/grpo_groups", 1)
        while self.pending_steps > self.max_pending and (self.waiting or self.ready):
            if self.waiting:  # the oldest unfinished group first (dicts keep insertion order)
                group = list(self.waiting.pop(next(iter(self.waiting))).values())
            else:
                group = self.ready.popleft()
                self.ready_steps -= sum(e.decisions for e in group)
            self.pending_steps -= sum(e.decisions for e in group)
            self.count("train/grpo_groups_dropped_overflow", 1)

    def segments(self) -> list[TrajectorySegment]:
        """Every buffered segment (complete groups, then waiting episodes, then unfinished ones), each
        episode's in order: added again in this order, they rebuild the same groups."""
        episodes = [e for group in self.ready for e in group] + [e for m in self.waiting.values() for e in m.values()]
        return [s for e in episodes for s in e.segments] + [s for segs in self.open.values() for s in segs]

    def _drop_open(self, env_id: int) -> None:
        segs = self.open.pop(env_id)
        self.pending_steps -= sum(len(s.obs) for s in segs)
        self.count("train/grpo_episodes_incomplete", 1)

    def take(self, version: int, batch_size: int) -> list[tuple[Episode, float, np.ndarray]]:
        """Complete groups, oldest first, until ``batch_size`` decisions: (episode, advantage, fresh mask)."""
        out, steps = [], 0
        while self.ready and steps < batch_size:
            group = self.ready.popleft()
            n = sum(e.decisions for e in group)
            self.ready_steps -= n
            self.pending_steps -= n
            advantages = group_advantages(np.array([e.ret for e in group]))
            for episode, adv in zip(group, advantages):
                fresh = version - episode.cat("versions") <= self.max_staleness
                if not fresh.all():
                    self.count("train/stale_dropped", int((~fresh).sum()))
                if fresh.any():
                    out.append((episode, float(adv), fresh))
                    steps += int(fresh.sum())
        return out

    @staticmethod
    def size(item: tuple[Episode, float, np.ndarray]) -> int:
        """Decisions of one item of ``take``."""
        return int(item[2].sum())

    @staticmethod
    def to_wire(item: tuple[Episode, float, np.ndarray]) -> dict[str, Any]:
        """One item of ``take`` as it travels between training ranks (``ebrl.algos.parallel``)."""
        episode, advantage, fresh = item
        return {"env_id": episode.env_id, "index": episode.index, "segments": [to_wire(s) for s in episode.segments],
                "advantage": float(advantage), "fresh": np.asarray(fresh, dtype=bool)}

    @staticmethod
    def from_wire(raw: Any) -> tuple[Episode, float, np.ndarray]:
        if not isinstance(raw, dict) or not isinstance(raw.get("segments"), list):
            raise MessageError(f"not a GRPO item: {type(raw).__name__}")
        segments = [from_wire(TrajectorySegment, s) for s in raw["segments"]]
        fresh = np.asarray(raw.get("fresh"), dtype=bool)
        if fresh.shape != (sum(len(s.obs) for s in segments),) or not math.isfinite(raw.get("advantage", math.nan)):
            raise MessageError("a GRPO item whose fresh mask or advantage does not fit its segments")
        return Episode(int(raw["env_id"]), int(raw["index"]), segments), float(raw["advantage"]), fresh

    def build(self, items: list[tuple[Episode, float, np.ndarray]], model: nn.Module) -> Batch:
        def cat(name: str) -> torch.Tensor:
            return torch.as_tensor(np.concatenate([e.cat(name)[mask] for e, _, mask in items]))

        advantages = np.concatenate([np.full(int(mask.sum()), adv, np.float32) for _, adv, mask in items])
        return Batch(obs=cat("obs"), actions=cat("actions"), latents=cat("latents"), logprobs=cat("logprobs"),
                     advantages=torch.as_tensor(advantages), returns=None, values=cat("values"),
                     versions=np.concatenate([e.cat("versions")[mask] for e, _, mask in items]),
                     normalize_advantages=False)
