"""Which observations generation serves next: the staleness bound, applied at the policy's side.

A group's chunk ``seq`` belongs to iteration ``seq // Schedule.length(live sim hosts)``; it is answered only
by a policy version at least ``iteration - max_staleness`` (``Schedule.min_version``). Observations that
would need a newer policy wait here — back-pressure on their group (it has one observation in flight at
most), never an unbounded buffer.
"""

from __future__ import annotations

import numpy as np

from ebrl.messages import Observation
from ebrl.sched.modes import Schedule


class ObservationQueue:
    """Observations received and not yet served, in arrival order: one per group (a group has one in flight;
    a newer one of the same group, e.g. sent again after a timeout, replaces it) and at most ``capacity``
    (beyond it the oldest is dropped, counted in ``dropped``): bounded whatever arrives."""

    def __init__(self, schedule: Schedule, obs_shape: tuple[int, ...] | None = None, capacity: int = 0):
        """``obs_shape``: the policy's observation shape; an observation of another shape, or with a value that
        is not finite (a sim checks its env's, ``ebrl.envs.guard``), is dropped, counted in ``bad``."""
        self.schedule, self.obs_shape = schedule, obs_shape
        self.capacity = capacity or 64 * schedule.groups  # room for the groups of many sim hosts
        self.waiting: dict[int, Observation] = {}  # group -> its observation, oldest first
        self.replaced = 0
        self.dropped = 0
        self.bad = 0
        self.lead = 0  # versions generation went back by (went_back): iterations the sims ran ahead meanwhile

    def __len__(self) -> int:
        return len(self.waiting)

    def extend(self, observations: list[Observation]) -> None:
        for m in observations:
            if (self.obs_shape is not None and tuple(m.obs.shape[1:]) != tuple(self.obs_shape)) \
                    or not np.isfinite(m.obs).all():
                self.bad += 1
                continue
            if self.waiting.pop(m.group, None) is not None:
                self.replaced += 1
            self.waiting[m.group] = m
            if len(self.waiting) > self.capacity:
                del self.waiting[next(iter(self.waiting))]
                self.dropped += 1

    def counters(self) -> dict[str, int]:
        """What gen reports: observations waiting for a newer policy, dropped beyond the capacity, and dropped as
        bad (shape, values)."""
        return {"obs_waiting_for_policy": len(self.waiting), "obs_waiting_dropped": self.dropped, "obs_dropped": self.bad}

    def went_back(self, old: int, new: int) -> None:
        """Generation went back from version ``old`` to ``new`` (it was ahead of training: a forged version,
        ``ebrl.weights``). The sims' iterations ran ahead with ``old``; the bound is kept from there on rather
        than waited out, which training, behind them, could never do."""
        self.lead += old - new

    def take(self, version: int, sim_hosts: int, max_groups: int) -> list[Observation]:
        """The next batch that policy ``version`` may answer: at most ``max_groups`` groups, oldest first."""
        version += self.lead
        batch = [m for m in self.waiting.values() if version >= self.schedule.min_version(m.seq, sim_hosts)]
        batch = batch[:max_groups]
        for m in batch:
            del self.waiting[m.group]
        return batch
