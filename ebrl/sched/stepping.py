"""How a group executes one action chunk on its env workers: three stepping policies.

* :class:`IndependentStepping` — every env runs its whole chunk on its own
  (statically pinned) worker; no barrier between envs.
* :class:`BatchStepping` — all envs of the group take step k, then a barrier,
  then step k+1 (vectorised-env stepping, what RLinf and gymnasium vector envs do).
* :class:`RebindingStepping` — step-level asynchrony with greedy core rebinding
  across all groups (:mod:`ebrl.sched.rebind`, carried out by the workers through
  :mod:`ebrl.resources.corepool`): one step at a time is bound to a free core of the
  simulation budget, longest-latency ready env first.

Each returns, per env, the merged :class:`ChunkResult` and the env's chunk
latency (chunk start to the env's last step). An env whose worker died or did
not answer within ``timeout`` seconds gets a :class:`WorkerFailed` in place of
its result; the other envs of the chunk carry on, and the caller replaces the
worker (``replace``).
"""

from __future__ import annotations

import asyncio
import collections
import time
from typing import Callable, Protocol, Sequence

import numpy as np

from ebrl.envs.worker import ChunkResult, EnvWorker, WorkerFailed, cores_used
from ebrl.resources.corepool import CorePool
from ebrl.sched.stepchoice import SteppingChoice


def merge(results: Sequence[ChunkResult]) -> ChunkResult:
    """Combine consecutive single-step results of one env into one chunk result."""
    last = results[-1]
    return ChunkResult(
        reward=float(sum(r.reward for r in results)),
        steps=int(sum(r.steps for r in results)),
        terminated=last.terminated,
        truncated=last.truncated,
        final_obs=last.final_obs,
        next_obs=last.next_obs,
        episode_return=last.episode_return,
        episode_length=last.episode_length,
        episode_success=last.episode_success,
        busy_s=float(sum(r.busy_s for r in results)),
        episode=results[0].episode,
        step_s=tuple(t for r in results for t in r.step_s),
        step_cpu_s=tuple(t for r in results for t in r.step_cpu_s),
        cores=tuple(c for r in results for c in r.cores),
        helper_cpu_s=float(sum(r.helper_cpu_s for r in results)),
    )


Result = ChunkResult | WorkerFailed


class Stepping(Protocol):
    timeout: float | None  # seconds a worker may take for one request before it counts as hung

    async def run_chunk(self, workers: Sequence[EnvWorker],
                        actions: np.ndarray) -> tuple[list[Result], list[float]]: ...


class IndependentStepping:
    timeout: float | None = None

    async def run_chunk(self, workers, actions):
        start = time.perf_counter()
        latencies = [0.0] * len(workers)

        async def one(i: int) -> Result:
            try:
                result = await workers[i].chunk(actions[i], timeout=self.timeout)
            except WorkerFailed as exc:
                self.failed(workers[i])
                return exc
            latencies[i] = time.perf_counter() - start
            return result

        results = await asyncio.gather(*(one(i) for i in range(len(workers))))
        return list(results), latencies

    def failed(self, worker: EnvWorker) -> None:
        """A worker died or hung: the caller replaces it once the chunk is done."""


class BatchStepping:
    timeout: float | None = None

    async def run_chunk(self, workers, actions):
        start = time.perf_counter()
        steps: list[list[ChunkResult]] = [[] for _ in workers]
        failed: dict[int, WorkerFailed] = {}
        latencies = [0.0] * len(workers)
        active = list(range(len(workers)))
        for k in range(actions.shape[1]):
            if not active:
                break
            last = k == actions.shape[1] - 1
            results = await asyncio.gather(*(workers[i].chunk(actions[i, k:k + 1], observe=last,
                                                              timeout=self.timeout)
                                             for i in active), return_exceptions=True)  # barrier
            now = time.perf_counter()
            still = []
            for i, result in zip(active, results):
                if isinstance(result, WorkerFailed):
                    failed[i] = result
                    continue
                if isinstance(result, BaseException):
                    raise result
                steps[i].append(result)
                latencies[i] = now - start
                if not (result.terminated or result.truncated):
                    still.append(i)
            active = still
        return [failed[i] if i in failed else merge(s) for i, s in enumerate(steps)], latencies


class RebindingStepping(IndependentStepping):
    """Step-level asynchrony with greedy core rebinding: one instance serves every group of the sim service,
    whose env workers share one :class:`~ebrl.resources.corepool.CorePool`. Each env gets its whole chunk at once;
    the workers claim a core per step from the pool and hand cores to each other (the ready set spans all
    groups), so no single step passes through the event loop."""

    def __init__(self, pool: CorePool, on_step: Callable[[int, float], None] | None = None,
                 choice: SteppingChoice | None = None, on_mode: Callable[[int, float, float], None] | None = None,
                 on_decision: Callable[[str], None] | None = None):
        self.pool = pool
        self.on_step = on_step  # (core, seconds) after every chunk: per-core busy time
        self.choice = choice  # sim.core_rebinding = "auto": the pool's mode is chosen by measuring
        self.on_mode, self.on_decision = on_mode, on_decision  # (mode, start, end) of a period; a decision
        self._mode_since: float | None = None  # from the first chunk on
        if choice is not None:
            pool.set_mode(choice.mode)

    async def run_chunk(self, workers, actions):
        results, latencies = await super().run_chunk(workers, actions)
        now = time.monotonic()
        busy: dict[int, float] = collections.defaultdict(float)
        for result, latency in zip(results, latencies):
            if not isinstance(result, ChunkResult):
                continue
            for core, seconds in zip(result.cores, result.step_s):
                busy[core] += seconds
            if self.choice is not None:
                self.choice.observe(now, result.steps, result.step_cpu_s, latency, cores_used([result]))
        if self.on_step is not None:  # once per core and chunk, not per step
            for core, seconds in busy.items():
                self.on_step(core, seconds)
        if self.choice is not None:
            self._follow(now)
        return results, latencies

    def _follow(self, now: float) -> None:
        """Apply the choice's mode; report each period spent in a mode (at most 5 s each) and each decision."""
        choice, before = self.choice, self.choice.mode
        decision = choice.tick(now)
        wall = time.time()
        if self._mode_since is None:
            self._mode_since = wall
        if self.on_mode is not None and (choice.mode != before or wall - self._mode_since >= 5.0):
            self.on_mode(before, self._mode_since, wall)
            self._mode_since = wall
        if choice.mode != before:
            self.pool.set_mode(choice.mode)
        if decision and self.on_decision is not None:
            self.on_decision(decision)

    def failed(self, worker: EnvWorker) -> None:
        """At once, not when the chunk is done: a dead or hung worker may hold a core the other envs of the
        chunk wait for. It is killed (it is replaced anyway) and what it held goes to them."""
        worker.kill()
        self.pool.reclaim(worker.slot)

    def set_budget(self, cores: list[int]) -> None:
        self.pool.set_budget(cores)

    def metrics(self) -> dict[str, float]:
        handoffs, rebinds, gap = self.pool.counters()
        out = {"sim/rebinds": float(rebinds), "sim/core_handoffs": float(handoffs)}
        if handoffs:
            out["sim/handoff_gap_us"] = gap * 1e6
        if self.choice is not None:
            out.update(self.choice.metrics())
        return out
