"""A training rank's update cycle, seen from the event loop (the train service drives it, ``ebrl/services/train.py``).

Rank 0 learns whenever a full batch is pending: segments arrive all the time (also during an update), a
batch becomes ready as they do, and the cycle waits for it, takes it and updates on the learner's one update
thread, then writes a checkpoint when ``train.checkpoint_every`` says one is due. With several ranks the others
wait in a collective meanwhile, so a wait for data sends them a keep-alive every ``KEEPALIVE_S``
(``ebrl.algos.ranks``). Stopping, the ranks wind down in an order that leaves none of them in a collective.
"""

from __future__ import annotations

import asyncio
import concurrent.futures
from typing import TYPE_CHECKING, Callable

from ebrl.algos import saving
from ebrl.algos.parallel import KEEPALIVE_S
from ebrl.messages import SegmentBatch, TrajectorySegment

if TYPE_CHECKING:
    from ebrl.algos.learner import Learner
    from ebrl.algos.ranks import Ranks


class UpdateCycle:
    """Rank 0's cycle: ``accept`` segments, ``next_items`` once a batch is ready, ``checkpoint`` after an update."""

    def __init__(self, learner: Learner, pool: concurrent.futures.ThreadPoolExecutor, ranks: Ranks | None):
        self.learner, self.pool, self.ranks = learner, pool, ranks
        self.enough = asyncio.Event()  # a full batch is pending
        if learner.ready:  # from what the learner before handed over
            self.enough.set()

    def accept(self, item: TrajectorySegment | SegmentBatch, malformed: Callable[[Exception], None]) -> None:
        """A segment, or a group's packed segments, into the learner's bounded collector (``Learner.accept``:
        dropped, counted, if bad)."""
        if self.learner.accept(item, malformed) and self.learner.ready:
            self.enough.set()

    async def next_items(self) -> list:
        """The next update's items once a batch is ready; none where everything pending was too stale, or where
        the other ranks got a keep-alive instead (after ``KEEPALIVE_S`` without a batch)."""
        try:
            await asyncio.wait_for(self.enough.wait(), KEEPALIVE_S if self.ranks else None)
        except asyncio.TimeoutError:
            await self.ranks.keepalive()
            return []
        items = self.learner.take()
        if not self.learner.ready:
            self.enough.clear()
        return items

    async def checkpoint(self, run_name: str) -> None:
        """After an update: the training state, on the update thread, where ``train.checkpoint_every`` says."""
        if saving.checkpoint_due(self.learner.cfg.train.checkpoint_every, self.learner.version):
            await asyncio.get_running_loop().run_in_executor(self.pool, self.learner.save_checkpoint, run_name)


async def wind_down(learner: Learner, pool: concurrent.futures.ThreadPoolExecutor, ranks: Ranks | None) -> None:
    """A stopping rank's update thread and training group: a rank > 0 first follows rank 0 up to its stop
    (``Ranks.drain``), an update in flight ends, then rank 0 releases the others (``Ranks.stop``) and every
    rank leaves the group."""
    if learner.rank > 0 and ranks:
        await ranks.drain()
    learner.algo.stop()  # an update waiting on the algorithm's own (the replay) ends
    await asyncio.to_thread(pool.shutdown, wait=True, cancel_futures=True)  # an update in flight ends
    if ranks and learner.rank == 0:
        await ranks.stop()
    if ranks:
        learner.dp.close()
