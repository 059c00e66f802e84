"""Which observations generation serves next: the staleness bound, applied at the policy's side.

A group's chunk ``seq`` belongs to iteration ``seq // Schedule.length(live sim hosts)``; it is answered only
by a policy version at least ``iteration - max_staleness`` (``Schedule.min_version``). Observations that
would need a newer policy wait here — back-pressure on their group (it has one observation in flight at
most), never an unbounded buffer.
"""

from __future__ import annotations

from ebrl.messages import Observation
from ebrl.sched.modes import Schedule


class ObservationQueue:
    """Observations received and not yet served, in arrival order."""

    def __init__(self, schedule: Schedule):
        self.schedule = schedule
        self.waiting: list[Observation] = []

    def __len__(self) -> int:
        return len(self.waiting)

    def extend(self, observations: list[Observation]) -> None:
        self.waiting.extend(observations)

    def take(self, version: int, sim_hosts: int, max_groups: int) -> list[Observation]:
        """The next batch that policy ``version`` may answer: at most ``max_groups`` groups, oldest first."""
        batch = [m for m in self.waiting if version >= self.schedule.min_version(m.seq, sim_hosts)][:max_groups]
        served = {id(m) for m in batch}
        self.waiting = [m for m in self.waiting if id(m) not in served]
        return batch
