"""Bounded staleness on the training side: cut decisions older than the bound off a segment, and split a segment
where an update's batch ends."""

from __future__ import annotations

import dataclasses

from ebrl.messages import TrajectorySegment

PER_DECISION = ("obs", "actions", "latents", "logprobs", "values", "rewards", "steps", "versions")


def fresh_suffix(seg: TrajectorySegment, version: int, max_staleness: int) -> tuple[TrajectorySegment | None, int]:
    """The part of ``seg`` that an update at ``version`` may learn from, and how many decisions were cut.

    A decision made by policy version v is fresh if ``version - v <= max_staleness``. Versions never
    decrease along a segment, so the fresh decisions are a suffix; GAE of a suffix is exact (it only
    looks forward), so cutting the stale prefix loses nothing else."""
    if version - int(seg.versions.min()) <= max_staleness:  # all fresh (the common case, one reduction)
        return seg, 0
    keep = int((version - seg.versions <= max_staleness).sum())
    if keep == 0:
        return None, len(seg.obs)
    start = len(seg.obs) - keep
    return _decisions(seg, slice(start, None)), start


def split(seg: TrajectorySegment, n: int) -> tuple[TrajectorySegment, TrajectorySegment]:
    """``seg``'s first ``n`` decisions and the rest, 0 < n < len(seg.obs). The first part ends "cut" and
    bootstraps from the observation the rest starts with, as a segment cut at ``sim.segment_length`` does; the
    episodes that finished inside ``seg`` finished at its end, so they stay with the rest. For training's
    segments, whose camera bytes were joined back into ``obs`` on receipt (``obswire.decoder``), as for
    :func:`fresh_suffix`."""
    first = dataclasses.replace(_decisions(seg, slice(None, n)), end="cut", last_obs=seg.obs[n],
                                episode_returns=[], episode_lengths=[], episode_successes=[])
    return first, _decisions(seg, slice(n, None))


def _decisions(seg: TrajectorySegment, part: slice) -> TrajectorySegment:
    """``seg`` with ``part`` of each per-decision field."""
    return dataclasses.replace(seg, **{name: getattr(seg, name)[part] for name in PER_DECISION})
