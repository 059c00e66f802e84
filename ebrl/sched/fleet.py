"""One simulator host's environments: a worker process per env, grouped, stepped by the schedule's policy.

Group and env ids follow the host's place in the run (sim instance ``i`` of a multi-host run owns groups
``i * groups ...``), so every one is unique in the run: group ids name bus keys, env ids seed the envs.

A worker that dies or hangs is replaced (``recover``); an env whose workers fail ``MAX_REPLACEMENTS + 1`` times
in a row without answering one chunk (an env that raises at every step) is given up instead of being replaced
forever: its worker is gone, it takes no more chunks, the other envs go on (``given_up``, ``given_up_env``).
With GRPO groups (``share`` > 1) its group-mates on this host are given up with it: their episodes could never
be compared without it.
"""

from __future__ import annotations

import asyncio
import collections
import dataclasses
import logging
import os
import time
from typing import Callable, Iterable

import numpy as np

from ebrl.envs import EnvSpec, EnvWorker
from ebrl.envs.vector import InlineVectorWorker, VectorWorker
from ebrl.envs.worker import ChunkResult, VectorChunk, WorkerFailed
from ebrl.messages import EPISODES_MAX, RETURN_WINDOW, EpisodeBatch
from ebrl.resources.corepool import CorePool
from ebrl.sched.modes import Schedule, home_cores
from ebrl.sched.rollout import Episodes
from ebrl.sched.stepchoice import SteppingChoice
from ebrl.sched.stepping import BatchStepping, IndependentStepping, RebindingStepping, Result, Stepping

log = logging.getLogger(__name__)

ENV_SEED_STRIDE = 100_003  # env i's worker seed: run.seed * ENV_SEED_STRIDE + i
MAX_REPLACEMENTS = 5  # replacements of an env's worker in a row, none answering a chunk, before it is given up


class EnvFleet:
    """The env workers of ``schedule.groups`` groups, the stepping policy that runs their chunks, and the
    episode bookkeeping (GRPO: ``share`` envs start from the same states and finish episodes together)."""

    def __init__(self, spec: EnvSpec, schedule: Schedule, host: int, seed: int, share: int = 1,
                 on_core_step: Callable[[int, float], None] | None = None,
                 on_mode: Callable[[int, float, float], None] | None = None,
                 on_decision: Callable[[str], None] | None = None):
        """With rebinding, ``on_core_step(core, seconds)`` after each chunk for each core its envs stepped on;
        under ``sim.core_rebinding = "auto"``, ``on_mode(mode, start, end)`` for each period in a mode and
        ``on_decision(text)`` for each choice."""
        self._place(spec, schedule, host, seed, share)
        per = self.per_group
        self.pool: CorePool | None = None
        if schedule.core_rebinding:
            self.pool = CorePool(schedule.groups * per, schedule.sim_cores)
            choice = SteppingChoice(time.monotonic()) if schedule.rebinding_auto else None
            self.stepping: Stepping = RebindingStepping(self.pool, on_step=on_core_step, choice=choice,
                                                        on_mode=on_mode, on_decision=on_decision)
        else:
            self.stepping = IndependentStepping() if schedule.stepping == "async" else BatchStepping()
        self.workers: dict[int, list[EnvWorker]] = {}  # a given-up env keeps its dead worker's handle
        for g in self.groups:
            self.workers[g] = [self._start(env) for env in self.env_ids(g)]

    def _place(self, spec: EnvSpec, schedule: Schedule, host: int, seed: int, share: int) -> None:
        """What every fleet keeps: this host's groups and env ids, the episode bookkeeping, the failure counts."""
        self.spec = dataclasses.replace(spec, lazy_render=schedule.lazy_render)  # the mode's rendering
        self.schedule, self.seed = schedule, seed
        first = host * schedule.groups
        self.groups = list(range(first, first + schedule.groups))
        per = self.per_group = schedule.envs_per_group
        self.episodes = Episodes(range(first * per, (first + schedule.groups) * per), share)
        self.failures: dict[int, int] = {}  # env (a group, vectorized) -> failures in a row without a chunk answered
        self.given_up_envs: set[int] = set()
        self.given_up = 0  # envs given up (sim/envs_given_up)

    async def reset_group(self, g: int) -> np.ndarray:
        """Start every env of group ``g`` (episode 0); their first observations, [envs, ...]."""
        return np.stack(await asyncio.gather(*(w.reset() for w in self.workers[g])))

    async def run_chunk(self, g: int, active: list[int], actions: np.ndarray) -> tuple[list[Result], list[float]]:
        """Envs ``active`` (indices into group ``g``) run ``actions`` (one chunk each); per env, its result (or
        the :class:`WorkerFailed` of a worker to recover) and its chunk latency."""
        return await self.stepping.run_chunk([self.workers[g][i] for i in active], actions)

    def saw_version(self, version: int) -> None:
        """A chunk acted by policy ``version`` arrived: the stepping choice waits for training's steady state."""
        if (rebinding := self.rebinding) is not None and rebinding.choice is not None:
            rebinding.choice.saw_version(time.monotonic(), version)

    @property
    def rebinding(self) -> RebindingStepping | None:
        return self.stepping if isinstance(self.stepping, RebindingStepping) else None

    def env_ids(self, g: int) -> np.ndarray:
        return np.arange(g * self.per_group, (g + 1) * self.per_group, dtype=np.int64)

    def env_seed(self, env: int) -> int:
        """GRPO compares rollouts from the same initial states: a group's envs share reset seeds."""
        return self.seed * ENV_SEED_STRIDE + self.episodes.members(env)[0]

    def slot(self, env: int) -> int:
        """The env's place in this host's core pool (its envs numbered from 0)."""
        return env - self.groups[0] * self.per_group

    def _start(self, env: int, core: int | tuple[int, ...] | None = None) -> EnvWorker:
        if self.pool is not None:  # every step claims a core of the pool
            return EnvWorker(self.spec, seed=self.env_seed(env), pool=self.pool, slot=self.slot(env),
                             nice=self.schedule.nice)
        # static pinning round-robin over them (sets of sim.cores_per_env cores for a multi-threaded simulator)
        home = home_cores(self.schedule.sim_cores, self.schedule.cores_per_env, env) if core is None else core
        return EnvWorker(self.spec, seed=self.env_seed(env), core=home, nice=self.schedule.nice)

    def replace(self, g: int, i: int) -> EnvWorker:
        """Kill env ``i`` of group ``g``'s worker (dead or hung); a new one for the same env, seed and core
        (or place in the core pool, whose cores the old one held go to the others)."""
        old = self._stop(g, i)
        worker = self.workers[g][i] = self._start(int(self.env_ids(g)[i]), old.core)
        return worker

    async def recover(self, g: int, i: int, episode: int) -> np.ndarray | None:
        """After env ``i`` of group ``g``'s worker failed: replace it and start episode ``episode`` on the new
        one (one that fails at once is replaced again); its first observation. None: the env is given up, now
        (``MAX_REPLACEMENTS``, logged) or before, and has no worker any more."""
        env = int(self.env_ids(g)[i])
        while env not in self.given_up_envs:
            failed = self.workers[g][i]
            failures = self.failures[env] = (0 if failed.chunks_done else self.failures.get(env, 0)) + 1
            if failures > MAX_REPLACEMENTS:
                self._give_up(env, failures)
                break
            try:
                return await self.replace(g, i).reset(episode)  # type: ignore[return-value]
            except WorkerFailed as exc:
                log.warning("env %d: its new worker failed at once (%s)", env, exc)
        self._stop(g, i)
        return None

    def _stop(self, g: int, i: int, close_pipe: bool = True) -> EnvWorker:
        """Kill env ``i`` of group ``g``'s worker; the cores it held in the pool go to the others."""
        worker = self.workers[g][i]
        worker.kill(close_pipe)
        if self.pool is not None:
            self.pool.reclaim(self.slot(int(self.env_ids(g)[i])))
        return worker

    def given_up_env(self, env: int) -> bool:
        """Whether env ``env`` was given up: it takes no more chunks."""
        return env in self.given_up_envs

    def _give_up(self, env: int, failures: int) -> None:
        mates = [m for m in self.episodes.members(env)  # GRPO: the group-mates on this host, itself included
                 if m // self.per_group in self.workers and m not in self.given_up_envs]
        with_mates = f"; with it its GRPO group-mates {[m for m in mates if m != env]}" if len(mates) > 1 else ""
        log.error("env %d given up: its worker failed %d times in a row without answering a chunk (after %d "
                  "replacements)%s; the other envs go on", env, failures, failures - 1, with_mates)
        for mate in mates:
            self.given_up_envs.add(mate)
            self.given_up += 1
            if mate != env:  # its worker goes too: a chunk in flight fails, and the worker is not replaced
                self._stop(*divmod(mate, self.per_group), close_pipe=False)  # closed by recover(), or close()

    def live(self) -> list[EnvWorker]:
        """The workers of the envs not given up."""
        return [w for g in self.groups for env, w in zip(self.env_ids(g), self.workers[g])
                if int(env) not in self.given_up_envs]

    def count(self) -> int:
        """Envs running (not given up)."""
        return len(self.live())

    def niceness(self) -> float | None:
        """The lowest niceness of the env workers' processes (None: none is alive)."""
        return lowest_niceness(worker.proc.pid for worker in self.live())

    def cores(self) -> list[int]:
        """The cores the envs run on (a rebinding budget, or the statically pinned cores)."""
        if self.pool is not None:
            return self.pool.cores()
        return sorted({c for w in self.live() for c in w.home})

    def pin(self, cores: list[int]) -> None:
        """A new simulation core budget: rebinding uses it from the next step; static pinning re-pins (every
        thread of each worker, on ``sim.cores_per_env`` cores each)."""
        if self.pool is not None:
            self.pool.set_budget(cores)
            return
        for i, worker in enumerate(self.live()):
            worker.pin(home_cores(cores, self.schedule.cores_per_env, i))

    def close(self) -> None:
        for workers in self.workers.values():
            for worker in workers:
                worker.close(timeout=1.0)


class VectorFleet(EnvFleet):
    """``sim.vectorized``: each group one :class:`~ebrl.envs.vector.VectorWorker` process stepping its envs as one
    batch (ManiSkill on GPU PhysX, or copies of the env in one process), on the whole simulation core budget.

    A group's process that dies or hangs is replaced as a whole: every env of the group gets the failure, the
    first to recover starts the new process, and each env's episode in progress is dropped (its numbering goes
    on). A group whose process fails ``MAX_REPLACEMENTS + 1`` times in a row without answering a chunk is given up."""

    def __init__(self, spec: EnvSpec, schedule: Schedule, host: int, seed: int, share: int = 1, obs_size: int = 0,
                 inline: bool = False, **_: object):
        """``obs_size``: values per observation; observations then come back through shared memory. ``inline``:
        each group steps on a thread of this process instead (:class:`~ebrl.envs.vector.InlineVectorWorker`: the
        simulator shares a process with generation and training)."""
        self.inline = inline
        if share > 1:
            raise ValueError("vectorized groups cannot promise GRPO's shared initial states (sim.vectorized)")
        self._place(spec, schedule, host, seed, share)
        self.obs_size = obs_size
        self.pool = None
        self.stepping = IndependentStepping()  # its timeout: how long a batch may take for one chunk
        self.fresh: dict[int, np.ndarray] = {}  # group -> first observations of its new process, while recovering
        self.vectors = {g: self._start_group(g) for g in self.groups}
        self.workers = {}  # no process per env

    def _start_group(self, g: int) -> VectorWorker | InlineVectorWorker:
        seeds = [self.env_seed(int(env)) for env in self.env_ids(g)]
        if self.inline:  # a thread of the shared process: no niceness of its own
            return InlineVectorWorker(self.spec, seeds, self.schedule.sim_cores, self.obs_size)
        return VectorWorker(self.spec, seeds, self.schedule.sim_cores, self.obs_size, nice=self.schedule.nice)

    async def reset_group(self, g: int) -> np.ndarray:
        return await self.vectors[g].reset(np.zeros(self.per_group, np.int64))

    async def run_chunk(self, g: int, active: list[int], actions: np.ndarray) -> tuple[list[Result], list[float]]:
        if len(active) != self.per_group:
            raise ValueError(f"group {g}: a vectorized batch steps all of its {self.per_group} envs, not {len(active)}")
        chunk, latency = await self.run_vector_chunk(g, actions)
        if isinstance(chunk, WorkerFailed):
            return [chunk] * len(active), [0.0] * len(active)
        return list(chunk.results()), [latency] * len(active)

    async def run_vector_chunk(self, g: int, actions: np.ndarray) -> tuple[VectorChunk | WorkerFailed, float]:
        """Group ``g``'s batch steps ``actions`` ([N, K, A]): what it did as one :class:`VectorChunk` and the
        chunk's wall seconds, or the :class:`WorkerFailed` of its process (killed: every env then recovers)."""
        start = time.perf_counter()
        try:
            chunk = await self.vectors[g].chunk(actions, timeout=self.stepping.timeout)
        except WorkerFailed as exc:
            self.vectors[g].kill()
            return exc, 0.0
        return chunk, time.perf_counter() - start

    async def recover(self, g: int, i: int, episode: int) -> np.ndarray | None:
        """After group ``g``'s process failed: the first env to ask starts a new process for the whole group, every
        env on the next episode of its own (``episode`` for env ``i``); env ``i``'s first observation. None: the
        group is given up."""
        env = int(self.env_ids(g)[i])
        if env in self.given_up_envs:
            return None
        if g not in self.fresh:
            episodes = np.asarray([self.episodes.index[int(e)] + 1 for e in self.env_ids(g)], np.int64)
            episodes[i] = episode
            while True:
                failed = self.vectors[g]
                failures = self.failures[g] = (0 if failed.chunks_done else self.failures.get(g, 0)) + 1
                if failures > MAX_REPLACEMENTS:
                    failed.kill()
                    log.error("group %d given up: its process failed %d times in a row without answering a chunk "
                              "(after %d replacements); the other groups go on", g, failures, failures - 1)
                    for mate in self.env_ids(g):
                        self.given_up_envs.add(int(mate))
                        self.given_up += 1
                    return None
                failed.kill()
                self.vectors[g] = self._start_group(g)
                try:
                    self.fresh[g] = await self.vectors[g].reset(episodes)
                    break
                except WorkerFailed as exc:
                    log.warning("group %d: its new process failed at once (%s)", g, exc)
        obs = self.fresh[g][i]
        if i == self.per_group - 1:  # the last env of the group has its observation: recovery is done
            del self.fresh[g]
        return obs

    def live(self) -> list[VectorWorker]:  # type: ignore[override]
        return [self.vectors[g] for g in self.groups if int(self.env_ids(g)[0]) not in self.given_up_envs]

    def niceness(self) -> float | None:
        """The lowest niceness of the groups' processes (None: none, or they step on a thread of this process)."""
        return lowest_niceness(worker.proc.pid for worker in self.live() if isinstance(worker, VectorWorker))

    def count(self) -> int:
        return len(self.live()) * self.per_group

    def cores(self) -> list[int]:
        return sorted({core for worker in self.live() for core in worker.cores})

    def pin(self, cores: list[int]) -> None:
        for worker in self.live():
            worker.pin(cores)

    def close(self) -> None:
        for worker in self.vectors.values():
            worker.close(timeout=1.0)


def lowest_niceness(pids: Iterable[int | None]) -> float | None:
    """The lowest niceness among processes ``pids`` as the kernel has it (None: none of them is alive)."""
    seen = []
    for pid in pids:
        try:
            if pid is not None:
                seen.append(os.getpriority(os.PRIO_PROCESS, pid))
        except (ProcessLookupError, PermissionError):
            continue
    return float(min(seen)) if seen else None


def make_fleet(spec: EnvSpec, schedule: Schedule, host: int, seed: int, share: int = 1, obs_size: int = 0,
               inline: bool = False, **hooks: Callable) -> EnvFleet:
    """The fleet of the schedule: vectorized groups (their observations through shared memory when ``obs_size``
    is given; each on a thread of this process with ``inline``), or a worker process per env."""
    if schedule.vectorized:
        return VectorFleet(spec, schedule, host=host, seed=seed, share=share, obs_size=obs_size, inline=inline)
    return EnvFleet(spec, schedule, host=host, seed=seed, share=share, **hooks)


class RolloutStats:
    """What the simulator reports of its episodes and chunks: the last 20 returns and successes, and the
    latency of the last 1000 env chunks (which also sets how long a step may take before its worker counts
    as hung)."""

    def __init__(self, step_timeout: float = 0.0):
        self.configured_timeout = step_timeout  # sim.step_timeout; 0: derived from the chunk latencies
        self.returns: collections.deque[float] = collections.deque(maxlen=RETURN_WINDOW)
        self.successes: collections.deque[bool] = collections.deque(maxlen=RETURN_WINDOW)
        self.chunk_latency: collections.deque[float] = collections.deque(maxlen=1000)
        self.env_steps = 0  # this instance's env steps (what sim/env_steps counts)
        # every episode that ended since the last EpisodeBatch, the newest EPISODES_MAX of them
        self.episodes: collections.deque[tuple] = collections.deque(maxlen=EPISODES_MAX)
        self.episode_records_dropped = 0
        self.step_cpu_s = self.step_wall_s = 0.0  # since the last report: the envs' CPU (every thread), wall

    def chunk_done(self, result: ChunkResult) -> None:
        """One env's chunk: what ``sim/env_cores_used`` is measured from (:func:`ebrl.envs.worker.cores_used`)."""
        cpu, wall = result.stepped()
        self.step_cpu_s += cpu
        self.step_wall_s += wall

    def episode_ended(self, env: int, episode: int, ret: float, length: int, success: bool | None,
                      version: int) -> None:
        """One finished episode: into the windowed means and the next episode batch."""
        self.returns.append(ret)
        if success is not None:
            self.successes.append(success)
        if len(self.episodes) == self.episodes.maxlen:
            self.episode_records_dropped += 1
        self.episodes.append((env, episode, ret, length, success, version, self.env_steps, time.time()))

    def take_episodes(self, service: str, instance: int) -> EpisodeBatch | None:
        """The episodes that ended since the last call, as one message (None: none did)."""
        if not self.episodes:
            return None
        rows, self.episodes = list(self.episodes), collections.deque(maxlen=EPISODES_MAX)
        env, episode, ret, length, success, version, steps, end = (list(c) for c in zip(*rows))
        return EpisodeBatch(service=service, instance=instance, env_id=env, episode=episode, returns=ret,
                            length=length, success=success, policy_version=version, env_steps=steps, end_time=end)

    def step_timeout(self) -> float:
        if self.configured_timeout > 0:
            return self.configured_timeout
        if len(self.chunk_latency) < 50:
            return 120.0
        return max(20.0, 20 * float(np.percentile(self.chunk_latency, 99)))

    def metrics(self) -> dict[str, float]:
        out: dict[str, float] = {"sim/episode_records_dropped": float(self.episode_records_dropped)}
        if self.returns:
            out["sim/episode_return_mean"] = float(np.mean(self.returns))
        if self.successes:
            out["sim/success_rate"] = float(np.mean(self.successes))
        if self.step_wall_s > 0:  # cores an env keeps busy while it steps (above 1: a multi-threaded simulator)
            out["sim/env_cores_used"] = self.step_cpu_s / self.step_wall_s
            self.step_cpu_s = self.step_wall_s = 0.0
        if self.chunk_latency:
            lat = np.asarray(self.chunk_latency)
            out["sim/chunk_latency_avg_ms"] = float(lat.mean() * 1e3)
            out["sim/chunk_latency_p50_ms"] = float(np.percentile(lat, 50) * 1e3)
            out["sim/chunk_latency_p99_ms"] = float(np.percentile(lat, 99) * 1e3)
        return out

