"""Bounded staleness on the training side: cut decisions older than the bound off a segment."""

from __future__ import annotations

import dataclasses

from ebrl.messages import TrajectorySegment

PER_DECISION = ("obs", "actions", "latents", "logprobs", "values", "rewards", "steps", "versions")


def fresh_suffix(seg: TrajectorySegment, version: int, max_staleness: int) -> tuple[TrajectorySegment | None, int]:
    """The part of ``seg`` that an update at ``version`` may learn from, and how many decisions were cut.

    A decision made by policy version v is fresh if ``version - v <= max_staleness``. Versions never
    decrease along a segment, so the fresh decisions are a suffix; GAE of a suffix is exact (it only
    looks forward), so cutting the stale prefix loses nothing else."""
    keep = int((version - seg.versions <= max_staleness).sum())
    if keep == len(seg.obs):
        return seg, 0
    if keep == 0:
        return None, len(seg.obs)
    start = len(seg.obs) - keep
    return dataclasses.replace(seg, **{name: getattr(seg, name)[start:] for name in PER_DECISION}), start
