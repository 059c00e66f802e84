"""One simulator host's environments: a worker process per env, grouped, stepped by the schedule's policy.

Group and env ids follow the host's place in the run (sim instance ``i`` of a multi-host run owns groups
``i * groups ...``), so every one is unique in the run: group ids name bus keys, env ids seed the envs.
"""

from __future__ import annotations

import collections
from typing import Callable

import numpy as np

from ebrl.envs import EnvSpec, EnvWorker
from ebrl.sched.modes import Schedule
from ebrl.sched.rollout import Episodes
from ebrl.sched.stepping import BatchStepping, IndependentStepping, RebindingStepping, Stepping


class EnvFleet:
    """The env workers of ``schedule.groups`` groups, the stepping policy that runs their chunks, and the
    episode bookkeeping (GRPO: ``share`` envs start from the same states and finish episodes together)."""

    def __init__(self, spec: EnvSpec, schedule: Schedule, host: int, seed: int, share: int = 1,
                 on_core_step: Callable[[int, float], None] | None = None):
        self.spec, self.schedule, self.seed = spec, schedule, seed
        first = host * schedule.groups
        self.groups = list(range(first, first + schedule.groups))
        per = self.per_group = schedule.envs_per_group
        self.episodes = Episodes(range(first * per, (first + schedule.groups) * per), share)
        if schedule.core_rebinding:
            self.stepping: Stepping = RebindingStepping(schedule.sim_cores, on_step=on_core_step)
        else:
            self.stepping = IndependentStepping() if schedule.stepping == "async" else BatchStepping()
        self.workers: dict[int, list[EnvWorker]] = {}
        for g in self.groups:
            self.workers[g] = [self._start(env) for env in self.env_ids(g)]

    @property
    def rebinding(self) -> RebindingStepping | None:
        return self.stepping if isinstance(self.stepping, RebindingStepping) else None

    def env_ids(self, g: int) -> np.ndarray:
        return np.arange(g * self.per_group, (g + 1) * self.per_group, dtype=np.int64)

    def env_seed(self, env: int) -> int:
        """GRPO compares rollouts from the same initial states: a group's envs share reset seeds."""
        return self.seed * 100_003 + self.episodes.members(env)[0]

    def _start(self, env: int) -> EnvWorker:
        cores = self.schedule.sim_cores  # static pinning round-robin over them, unless steps are rebound
        worker = EnvWorker(self.spec, seed=self.env_seed(env),
                           core=None if self.rebinding is not None else cores[env % len(cores)])
        if self.rebinding is not None:
            self.rebinding.add(env, worker)
        return worker

    def replace(self, g: int, i: int) -> EnvWorker:
        """Kill env ``i`` of group ``g``'s worker (dead or hung); a new one for the same env, seed and core."""
        old = self.workers[g][i]
        old.kill()
        env = int(self.env_ids(g)[i])
        worker = EnvWorker(self.spec, seed=self.env_seed(env), core=old.core if self.rebinding is None else None)
        if self.rebinding is not None:
            self.rebinding.replace(env, worker)
        self.workers[g][i] = worker
        return worker

    def count(self) -> int:
        return sum(len(w) for w in self.workers.values())

    def cores(self) -> list[int]:
        """The cores the envs run on (a rebinding budget, or the statically pinned cores)."""
        if self.rebinding is not None:
            return sorted(self.rebinding.sched.budget)
        return sorted({w.core for ws in self.workers.values() for w in ws if w.core is not None})

    def pin(self, cores: list[int]) -> None:
        """A new simulation core budget: rebinding uses it from the next step; static pinning re-pins."""
        if self.rebinding is not None:
            self.rebinding.set_budget(cores)
            return
        for i, worker in enumerate(w for g in self.groups for w in self.workers[g]):
            worker.pin(cores[i % len(cores)])

    def close(self) -> None:
        for workers in self.workers.values():
            for worker in workers:
                worker.close(timeout=1.0)


class RolloutStats:
    """What the simulator reports of its episodes and chunks: the last 20 returns and successes, and the
    latency of the last 1000 env chunks (which also sets how long a step may take before its worker counts
    as hung)."""

    def __init__(self, step_timeout: float = 0.0):
        self.configured_timeout = step_timeout  # sim.step_timeout; 0: derived from the chunk latencies
        self.returns: collections.deque[float] = collections.deque(maxlen=20)
        self.successes: collections.deque[bool] = collections.deque(maxlen=20)
        self.chunk_latency: collections.deque[float] = collections.deque(maxlen=1000)

    def step_timeout(self) -> float:
        if self.configured_timeout > 0:
            return self.configured_timeout
        if len(self.chunk_latency) < 50:
            return 120.0
        return max(20.0, 20 * float(np.percentile(self.chunk_latency, 99)))

    def metrics(self) -> dict[str, float]:
        out: dict[str, float] = {}
        if self.returns:
            out["sim/episode_return_mean"] = float(np.mean(self.returns))
        if self.successes:
            out["sim/success_rate"] = float(np.mean(self.successes))
        if self.chunk_latency:
            lat = np.asarray(self.chunk_latency)
            out["sim/chunk_latency_avg_ms"] = float(lat.mean() * 1e3)
            out["sim/chunk_latency_p50_ms"] = float(np.percentile(lat, 50) * 1e3)
            out["sim/chunk_latency_p99_ms"] = float(np.percentile(lat, 99) * 1e3)
        return out

