"""gen's forward passes: where each runs, and how one pass's outputs go back to the groups it answers.

Forward passes run on one dedicated thread (``ebrl.threads.TorchPool``, with gen's torch threads); on the CPU, a
pass shorter than the hand-off to that thread and back runs on the event loop itself (:meth:`Forward.inline`).
Which observations a policy version may answer, and so what one batch holds, is ``ebrl.sched.batching``.
"""

from __future__ import annotations

import asyncio
import concurrent.futures
import time
from typing import TYPE_CHECKING, Any, Iterator

import numpy as np

from ebrl import devices
from ebrl.messages import ActionChunk, Observation

if TYPE_CHECKING:
    from ebrl.policies.graphs import Actor

INLINE_MAX_S = 0.002  # CPU forward passes shorter than this run on the event loop (``Forward.inline``)


class Forward:
    """``actor``'s passes on ``device`` (``ebrl.policies.graphs.Actor``: ``policy.dtype``, ``gen.compile``),
    each on the forward thread ``pool`` or inline."""

    def __init__(self, actor: Actor, device: Any, pool: concurrent.futures.ThreadPoolExecutor):
        self.actor, self.device, self.pool = actor, device, pool
        self.staging = devices.Staging(device)  # observations in through a pinned buffer on a GPU
        self.seconds = INLINE_MAX_S  # recent forward passes' seconds (an average); the first runs on the pool

    def __call__(self, obs: np.ndarray) -> tuple[np.ndarray, ...]:
        """One batch where it is called (the forward thread, or the loop): observations in, the policy's
        chunks back (actions, logprobs, values, latents)."""
        return self.actor(self.staging(obs))

    def inline(self) -> bool:
        """Run the next pass on the event loop: on the CPU, while passes take under ``INLINE_MAX_S``. The loop
        awaits the pass either way, and the hand-off to the forward thread and back (a wake-up each way) costs
        more than a small MLP's pass on loaded cores (``benchmarks/gen_handoff.py``)."""
        return self.device.type == "cpu" and self.seconds < INLINE_MAX_S

    async def timed(self, obs: np.ndarray) -> tuple[tuple[np.ndarray, ...], float, float]:
        """One batch, inline or on the forward thread as :meth:`inline` says; its outputs, and when the pass
        started and ended (wall clock)."""
        start = time.time()
        if self.inline():
            outputs = self(obs)
        else:
            outputs = await asyncio.get_running_loop().run_in_executor(self.pool, self, obs)
        end = time.time()
        self.seconds += 0.1 * (end - start - self.seconds)
        return outputs, start, end


def answers(batch: list[Observation], version: int, outputs: tuple[np.ndarray, ...]) -> Iterator[ActionChunk]:
    """Each observation's chunk of one pass's ``outputs`` (actions, logprobs, values, latents; the rows in the
    batch's order), made by policy ``version``."""
    actions, logprobs, values, latents = outputs
    row = 0
    for m in batch:
        n = len(m.env_ids)
        yield ActionChunk(group=m.group, seq=m.seq, policy_version=version, actions=actions[row:row + n],
                          logprobs=logprobs[row:row + n], values=values[row:row + n], latents=latents[row:row + n])
        row += n
