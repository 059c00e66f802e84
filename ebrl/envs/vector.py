"""Vectorized groups: one process steps all of a group's environments as one batch.

ManiSkill simulates hundreds to thousands of environments in one process on GPU PhysX (``sim_backend =
"physx_cuda"``); one environment per worker process, the CPU path, cannot use that. With ``sim.vectorized`` on (the
default under GPU PhysX), each group is one :class:`VectorWorker` process holding a batch of
``sim.envs_per_group`` environments:

* :class:`~ebrl.envs.batch.ManiSkillBatch` — ManiSkill's own batched environment: torch tensors on the simulator's device, partial
  resets through ``reset(options={"env_idx": ...})``;
* :class:`~ebrl.envs.batch.EnvBatch` — ``n`` copies of any backend's environment stepped one after another in one process (no
  process and pipe per environment: for environments whose steps cost microseconds).

A chunk steps the whole batch ``K`` times (:class:`~ebrl.envs.batch.BatchRunner`). An environment whose episode ends at step j < K
goes on being stepped with the chunk's remaining actions (a batch steps all of its environments or none); those
steps are not counted, their results are dropped, and the environment is reset once the chunk is done. So each
environment's :class:`~ebrl.envs.worker.ChunkResult` means what a worker process's does: the steps of one episode, up to its end,
with the first observation of the next. Rewards, ends and the observations stay on the simulator's device until
the chunk is done; then one copy brings them to the host: every environment's next observation, and the final
observation of those whose episode ended (the only ones that differ from it).
"""

from __future__ import annotations

import asyncio
import concurrent.futures
import logging
import os
import threading
from concurrent.futures import ThreadPoolExecutor
from multiprocessing.connection import Connection
from typing import Any

import numpy as np

from ebrl.envs.spec import EnvError, EnvSpec
from ebrl.envs.worker import VectorChunk, WorkerFailed, WorkerProcess, adopt, worker_context

log = logging.getLogger(__name__)


def _vector_main(conn: Connection, spec: EnvSpec, seeds: list[int], shared: Any = None,
                 owner: int | None = None, nice: int = 0) -> None:
    """A vectorized group's process: builds the batch, answers ``reset`` (each env's episode index) and ``chunk``
    (actions [N, K, A]) with a :class:`VectorChunk`, until ``close`` or its pipe closes. ``shared``: a float32
    buffer of 2 x N x D the observations go through instead of the pipe."""
    if not adopt(owner, nice):
        return
    from ebrl.envs.batch import BatchRunner, make_batch  # torch: in this process only

    batch = None
    try:
        batch = make_batch(spec, seeds)
        runner = BatchRunner(batch, spec.max_abs_reward)
        out = None if shared is None else np.frombuffer(shared, np.float32).reshape(2, len(seeds), -1)
        while True:
            try:
                cmd, arg = conn.recv()
            except (EOFError, OSError):
                return
            if cmd == "close":
                return
            try:
                reply: Any = runner.reset(arg, out) if cmd == "reset" else runner.chunk(arg, out) if cmd == "chunk" \
                    else ValueError(f"unknown worker command {cmd!r}")
            except (ValueError, EnvError) as exc:  # a malformed request: said, and the batch goes on
                reply = exc
            conn.send(reply)
    finally:
        if batch is not None:
            batch.close()


class VectorWorker(WorkerProcess):
    """Parent-side handle of a vectorized group's process: env ``i`` of the group is row ``i`` of its batch.

    With ``obs_size`` (values per observation), the observations come back through shared memory (2 x N x
    obs_size float32) rather than pickled through the pipe: for 256 envs of 64 px images (12.6 MB) that cut
    their way from the group's process to the sim service from 62 ms to 2.4 ms (benchmarks/vector_transfer.py)."""

    def __init__(self, spec: EnvSpec, seeds: list[int], cores: list[int], obs_size: int = 0, nice: int = 0):
        shared = worker_context(spec).RawArray("f", 2 * len(seeds) * obs_size) if obs_size else None
        super().__init__(spec, _vector_main, lambda child: (spec, list(seeds), shared), "ebrl-vector", nice)
        self.shared = None if shared is None else np.frombuffer(shared, np.float32).reshape(2, len(seeds), obs_size)
        self.num_envs = len(seeds)
        self.cores: list[int] = []
        self.pin(cores)

    def pin(self, cores: list[int]) -> None:
        """Run on ``cores`` (the simulation budget: a batch on the GPU still needs the CPU to drive it)."""
        os.sched_setaffinity(self.proc.pid, set(cores))
        self.cores = sorted(cores)

    async def reset(self, episodes: np.ndarray) -> np.ndarray:
        obs = await self.request("reset", np.asarray(episodes, np.int64))
        return self.shared[0].copy() if obs is None else obs  # type: ignore[return-value, index]

    async def chunk(self, actions: np.ndarray, timeout: float | None = None) -> VectorChunk:
        """The chunk's results, its observations copied out of the shared buffer (the next chunk overwrites it)."""
        result: VectorChunk = await self.request("chunk", np.asarray(actions, np.float32), timeout)  # type: ignore
        if result.next_obs is None:
            result.next_obs = self.shared[0].copy()  # type: ignore[index]
            result.final_obs = self.shared[1, :len(result.ended)].copy()  # type: ignore[index]
        self.chunks_done += 1
        return result


class InlineVectorWorker:
    """A vectorized group stepped on a thread of the sim service's own process, not a process of its own: where
    the simulator shares a process with generation and training (``run.processes``), its physics then runs in
    their CUDA context, not in one more. Every group of the process steps on one thread (:data:`PHYSICS`), one
    chunk at a time: MuJoCo Warp crashed with two groups stepping on two threads of one process, and on one GPU
    the groups' kernels queue one after another anyway; the groups still pipeline (one steps while another
    waits for its actions). The same interface as :class:`VectorWorker` (``reset``, ``chunk``, ``pin``, ``kill``,
    ``close``): a request that raises ``ValueError`` or ``EnvError`` is the batch's answer; any other failure, or
    no answer within the chunk's timeout, is a :class:`~ebrl.envs.worker.WorkerFailed`, after which the group is
    replaced by a new one. A thread that hangs cannot be killed: the groups behind it stop moving, and the stall
    watch restarts the whole process."""

    def __init__(self, spec: EnvSpec, seeds: list[int], cores: list[int], obs_size: int = 0):
        self.num_envs = len(seeds)
        self.cores: list[int] = []
        self.chunks_done = 0
        self.dead = False
        self.runner: Any = None
        self.built = physics().submit(self._build, spec, list(seeds))
        concurrent.futures.wait([self.built])  # built (and its CUDA graphs captured) before the caller goes on
        self.pin(cores)

    @property
    def thread_id(self) -> int | None:
        return _PHYSICS_THREAD[0]

    def _build(self, spec: EnvSpec, seeds: list[int]) -> None:
        from ebrl.envs.batch import BatchRunner, make_batch

        runner = BatchRunner(make_batch(spec, seeds), spec.max_abs_reward)
        if self.dead:  # killed while it was being built
            runner.batch.close()
        else:
            self.runner = runner

    def pin(self, cores: list[int]) -> None:
        """Run the physics thread on ``cores`` (as :meth:`VectorWorker.pin` its process; every group of the process
        is on the simulator's cores)."""
        self.cores = sorted(cores)
        if cores:
            physics().submit(os.sched_setaffinity, 0, set(cores))  # 0: the calling thread, on Linux; before the
            # next request on that thread, without waiting for the chunk in flight

    async def _request(self, what: str, arg: np.ndarray, timeout: float | None) -> Any:
        if self.dead:
            raise WorkerFailed(f"vectorized group is gone (it failed or hung before {what!r})")

        def run() -> Any:
            self.built.result()  # a batch that failed to build fails every request
            return self.runner.reset(arg) if what == "reset" else self.runner.chunk(arg)

        future = asyncio.wrap_future(physics().submit(run))
        try:
            return await asyncio.wait_for(asyncio.shield(future), timeout)
        except asyncio.TimeoutError:
            self.dead = True
            log.error("vectorized group did not answer %r within %.1f s on the physics thread", what, timeout)
            raise WorkerFailed(f"vectorized group did not answer {what!r} within {timeout:.1f} s") from None
        except (ValueError, EnvError):
            raise
        except Exception as exc:
            self.dead = True
            raise WorkerFailed(f"vectorized group failed: {exc!r}") from exc

    async def reset(self, episodes: np.ndarray) -> np.ndarray:
        return await self._request("reset", np.asarray(episodes, np.int64), None)

    async def chunk(self, actions: np.ndarray, timeout: float | None = None) -> VectorChunk:
        result = await self._request("chunk", np.asarray(actions, np.float32), timeout)
        self.chunks_done += 1
        return result

    def kill(self, close_pipe: bool = True) -> None:
        """Take no more requests; the batch is closed on the physics thread after what is queued there."""
        self.dead = True
        runner, self.runner = self.runner, None
        if runner is not None:
            physics().submit(runner.batch.close)

    def close(self, timeout: float = 2.0) -> None:
        self.kill()


_PHYSICS: list[ThreadPoolExecutor] = []
_PHYSICS_THREAD: list[int | None] = [None]


def physics() -> ThreadPoolExecutor:
    """The one thread of this process the in-process vectorized groups step on (:class:`InlineVectorWorker`)."""
    if not _PHYSICS:
        _PHYSICS.append(ThreadPoolExecutor(1, thread_name_prefix="ebrl-physics"))
        _PHYSICS[0].submit(lambda: _PHYSICS_THREAD.__setitem__(0, threading.get_native_id())).result()
    return _PHYSICS[0]
