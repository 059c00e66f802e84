"""How data-parallel training ranks move together (``train.world_size`` > 1), seen from the event loop.

Rank 0 leads: it scatters each update's shards (``Learner.update``), a keep-alive while it waits for data
and a stop at the end. The other ranks follow its commands one by one. Every collective runs on the
learner's one update thread, never on the event loop (``ebrl.algos.parallel`` has the collectives).
"""

from __future__ import annotations

import asyncio
import concurrent.futures
import logging
import time
from typing import Callable

from ebrl.algos.learner import Learner
from ebrl.algos.parallel import Command

log = logging.getLogger(__name__)


class Ranks:
    def __init__(self, learner: Learner, pool: concurrent.futures.ThreadPoolExecutor):
        self.learner, self.pool = learner, pool
        self.stopped = False  # rank 0 sent (or, on ranks > 0, received) the stop command
        self.receiving: concurrent.futures.Future | None = None
        self.stopping: asyncio.Future | None = None  # rank 0: the stop sequence, once begun

    async def keepalive(self) -> None:
        """Rank 0, waiting for data: the other ranks wait in a collective, tell them to go on."""
        await asyncio.get_running_loop().run_in_executor(self.pool, self.learner.dp.send, Command("idle"))

    async def follow_one(self, learned: Callable[[dict[str, float], float], None]) -> bool:
        """Ranks > 0: carry out rank 0's next command (``learned(losses, start)`` after an update); False once it
        said stop. A command being received when the task is cancelled is kept for the next call."""
        dp, loop = self.learner.dp, asyncio.get_running_loop()
        if self.receiving is None or self.receiving.cancelled():
            self.receiving = self.pool.submit(dp.receive)
        command = await asyncio.wrap_future(self.receiving)
        self.receiving = None
        if command.kind == "stop":
            # known at once: a stop of this rank during the gather below must not wait for another command
            # (the gather, already on the update thread, ends with rank 0's part; the teardown waits for it)
            self.stopped = True
            log.info("rank 0 said stop")
            if self.learner.sharded:  # rank 0 gathers the final training state: take part
                await loop.run_in_executor(self.pool, dp.checkpoint_state)
            return False
        if command.kind == "update":
            start = time.time()
            losses = await loop.run_in_executor(self.pool, self.learner.learn, command.items)
            learned(losses, start)
        return True

    async def drain(self) -> None:
        """Ranks > 0, stopping: finish what rank 0 started, up to its stop (rank 0 may be gone: give up)."""
        if self.stopped:
            return
        try:
            while await self.follow_one(lambda losses, start: None):
                pass
        except RuntimeError as exc:  # rank 0 is gone: the collective failed
            log.info("rank 0 is gone (%s); not waiting for its stop", exc)

    async def stop(self) -> None:
        """Rank 0: release the other ranks from their collective (once) and, sharded, gather the final
        training state with them; they may be gone (a crash): give up after a few seconds. The sequence runs
        to its end once begun: a run stopped between the stop command and the sharded gather (the launcher's
        stop right after the last update) would otherwise leave the other ranks in the gather, and the
        teardown's call would find the stop already sent. Every call awaits the same sequence."""
        if self.stopping is None:
            self.stopped = True
            self.stopping = asyncio.ensure_future(self._stop())
        await asyncio.shield(self.stopping)

    async def _stop(self) -> None:
        learner = self.learner
        try:
            # its own thread, not the update thread's pool: the teardown shuts that pool down, cancelling
            # what waits in it
            await asyncio.wait_for(asyncio.to_thread(learner.dp.send, Command("stop")), 5.0)
            if learner.sharded:
                state = await asyncio.wait_for(asyncio.to_thread(learner.dp.checkpoint_state), 30.0)
                learner.train_state = (learner.version, *state)
        except (asyncio.TimeoutError, RuntimeError) as exc:
            log.warning("could not stop the other training ranks cleanly: %r", exc)
