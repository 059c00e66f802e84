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
environment's :class:`ChunkResult` means what a worker process's does: the steps of one episode, up to its end,
with the first observation of the next. Rewards, ends and the observations stay on the simulator's device until
the chunk is done; then one copy brings them to the host: every environment's next observation, and the final
observation of those whose episode ended (the only ones that differ from it).
"""

from __future__ import annotations

import os
from dataclasses import dataclass
from multiprocessing.connection import Connection
from typing import Any

import numpy as np

from ebrl.envs.guard import Guarded
from ebrl.envs.spec import EnvError, EnvSpec
from ebrl.envs.worker import ChunkResult, WorkerProcess, adopt, worker_context


@dataclass
class VectorChunk:
    """What a batch did with one chunk, on the host: per env (``[N]``) and per env whose episode ended (``[E]``)."""

    reward: np.ndarray  # [N] sum over the env's counted steps
    steps: np.ndarray  # [N] steps counted (< K when its episode ended inside the chunk)
    terminated: np.ndarray  # [N] bool
    truncated: np.ndarray  # [N] bool
    episode: np.ndarray  # [N] the episode the steps belong to
    next_obs: np.ndarray | None  # [N, D] the observation for the next chunk (after the reset, where one ended)
    ended: np.ndarray  # [E] the envs whose episode ended
    final_obs: np.ndarray | None  # [E, D] their observation after their last step (before the reset)
    # (next_obs and final_obs are None while they travel in shared memory: VectorWorker.chunk fills them in)
    episode_return: np.ndarray  # [E]
    episode_length: np.ndarray  # [E]
    episode_success: np.ndarray  # [E] int8: 1, 0, or -1 where the task reports no success
    busy_s: float  # CPU seconds of the chunk's steps (the whole batch)
    step_s: tuple[float, ...]  # wall seconds of each batch step
    rewards_clipped: np.ndarray | None = None  # [N] steps whose reward was clipped (ebrl.envs.guard)
    rewards_nonfinite: np.ndarray | None = None  # [N] steps whose reward was not finite
    obs_nonfinite: np.ndarray | None = None  # [N] steps whose observation was not finite (its episode ended)

    def results(self) -> list[ChunkResult]:
        """One :class:`ChunkResult` per env, as a worker process would have answered; each env's share of the
        batch's CPU time as its ``busy_s``."""
        n = len(self.reward)
        row = {int(env): j for j, env in enumerate(self.ended)}
        out = []
        for i in range(n):
            j = row.get(i)
            success = None if j is None or self.episode_success[j] < 0 else bool(self.episode_success[j])
            out.append(ChunkResult(
                reward=float(self.reward[i]), steps=int(self.steps[i]), terminated=bool(self.terminated[i]),
                truncated=bool(self.truncated[i]), final_obs=self.next_obs[i] if j is None else self.final_obs[j],
                next_obs=self.next_obs[i], episode_return=None if j is None else float(self.episode_return[j]),
                episode_length=None if j is None else int(self.episode_length[j]), episode_success=success,
                busy_s=self.busy_s / n, episode=int(self.episode[i]), guarded=Guarded(
                    0 if self.rewards_clipped is None else int(self.rewards_clipped[i]),
                    0 if self.rewards_nonfinite is None else int(self.rewards_nonfinite[i]),
                    0 if self.obs_nonfinite is None else int(self.obs_nonfinite[i]))))
        return out


def _vector_main(conn: Connection, spec: EnvSpec, seeds: list[int], shared: Any = None,
                 owner: int | None = None) -> None:
    """A vectorized group's process: builds the batch, answers ``reset`` (each env's episode index) and ``chunk``
    (actions [N, K, A]) with a :class:`VectorChunk`, until ``close`` or its pipe closes. ``shared``: a float32
    buffer of 2 x N x D the observations go through instead of the pipe."""
    if not adopt(owner):
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

    def __init__(self, spec: EnvSpec, seeds: list[int], cores: list[int], obs_size: int = 0):
        shared = worker_context(spec).RawArray("f", 2 * len(seeds) * obs_size) if obs_size else None
        super().__init__(spec, _vector_main, lambda child: (spec, list(seeds), shared), "ebrl-vector")
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
