"""How a group executes one action chunk on its env workers: three stepping policies.

* :class:`IndependentStepping` — every env runs its whole chunk on its own
  (statically pinned) worker; no barrier between envs.
* :class:`BatchStepping` — all envs of the group take step k, then a barrier,
  then step k+1 (vectorised-env stepping, what RLinf and gymnasium vector envs do).
* :class:`RebindingStepping` — step-level asynchrony with greedy core rebinding
  across all groups (:mod:`ebrl.sched.rebind`): one step at a time is bound to a
  free core of the simulation budget, longest-latency ready env first.

Each returns, per env, the merged :class:`ChunkResult` and the env's chunk
latency (chunk start to the env's last step). An env whose worker died or did
not answer within ``timeout`` seconds gets a :class:`WorkerFailed` in place of
its result; the other envs of the chunk carry on, and the caller replaces the
worker (``replace``).
"""

from __future__ import annotations

import asyncio
import time
from typing import Callable, Protocol, Sequence

import numpy as np

from ebrl.envs.worker import ChunkResult, EnvWorker, WorkerFailed
from ebrl.sched.rebind import CoreRebinding


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
                return exc
            latencies[i] = time.perf_counter() - start
            return result

        results = await asyncio.gather(*(one(i) for i in range(len(workers))))
        return list(results), latencies


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


class RebindingStepping:
    """One instance serves every group of the sim service: the ready set spans all groups."""

    timeout: float | None = None

    def __init__(self, cores: list[int], on_step: Callable[[int, float], None] | None = None):
        self.sched = CoreRebinding(cores)
        self.on_step = on_step  # (core, seconds) after every step: per-core busy time
        self.workers: dict[int, EnvWorker] = {}
        self._env_by_worker: dict[int, int] = {}
        self._actions: dict[int, np.ndarray] = {}
        self._steps: dict[int, list[ChunkResult]] = {}
        self._done: dict[int, asyncio.Future] = {}
        self._tasks: set[asyncio.Task] = set()
        self.rebinds = 0

    def add(self, env: int, worker: EnvWorker) -> None:
        self.workers[env] = worker
        self._env_by_worker[id(worker)] = env
        self.sched.add_env(env)

    def replace(self, env: int, worker: EnvWorker) -> None:
        """A new worker for ``env`` (the old one failed); its chunk state was already closed."""
        del self._env_by_worker[id(self.workers[env])]
        self.workers[env] = worker
        self._env_by_worker[id(worker)] = env

    async def run_chunk(self, workers, actions):
        loop = asyncio.get_running_loop()
        start = time.perf_counter()
        envs = [self._env_by_worker[id(w)] for w in workers]
        futures = []
        for env, chunk in zip(envs, actions):
            self._actions[env] = chunk
            self._steps[env] = []
            self._done[env] = loop.create_future()
            futures.append(self._done[env])
            self.sched.submit_chunk(env, len(chunk))
        self._pump()
        finished = await asyncio.gather(*futures, return_exceptions=True)
        results: list[Result] = []
        for env, done in zip(envs, finished):
            steps = self._steps.pop(env)
            if isinstance(done, WorkerFailed):
                results.append(done)
            elif isinstance(done, BaseException):
                raise done
            else:
                results.append(merge(steps))
        return results, [t - start if isinstance(t, float) else 0.0 for t in finished]

    def set_budget(self, cores: list[int]) -> None:
        self.sched.set_budget(cores)
        self._pump()

    def _pump(self) -> None:
        for env, core in self.sched.dispatch():
            task = asyncio.ensure_future(self._step(env, core))
            self._tasks.add(task)
            task.add_done_callback(self._tasks.discard)

    async def _step(self, env: int, core: int) -> None:
        worker = self.workers[env]
        s = self.sched.envs[env].s
        t0 = time.perf_counter()
        try:
            if worker.core != core:
                try:
                    worker.pin(core)
                except OSError as exc:  # the process is gone
                    raise WorkerFailed(f"env worker {worker.proc.pid} cannot be pinned: {exc}") from None
                self.rebinds += 1
            chunk = self._actions[env]
            result = await worker.chunk(chunk[s:s + 1], observe=s == len(chunk) - 1, timeout=self.timeout)
        except Exception as exc:
            self.sched.complete(env, time.perf_counter() - t0, chunk_ended=True)
            self._done[env].set_exception(exc)
            self._pump()
            return
        latency = time.perf_counter() - t0
        if self.on_step is not None:
            self.on_step(core, latency)
        self._steps[env].append(result)
        if self.sched.complete(env, latency, chunk_ended=result.terminated or result.truncated):
            self._done[env].set_result(time.perf_counter())
        self._pump()
