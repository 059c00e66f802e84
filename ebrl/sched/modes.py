"""Execution modes (shared/DESIGN.md section 4): one function turns ``run.mode`` plus the ablation
switches into the concrete schedule every service follows.

| mode      | group pipeline | stepping              | rollout/train overlap | cores                      |
|-----------|----------------|-----------------------|-----------------------|----------------------------|
| ebrl      | yes            | async + core rebinding| yes (max_staleness)   | shared                     |
|           |                | (auto: where it pays) |                       |                            |
| colocated | no (one batch) | batch (barrier/step)  | no                    | shared                     |
| hybrid    | yes            | batch                 | no                    | shared                     |
| async     | no (one batch) | batch                 | yes (max_staleness)   | rollout and train disjoint |

Every mode but ebrl also renders every step's observation (``lazy_render``: RLinf's LIBERO env renders its
cameras at every step of a chunk). An explicit ``sim.stepping``, ``sim.core_rebinding``, ``sim.group_pipeline``,
``sim.lazy_render`` or ``train.overlap`` overrides the mode's choice (the ablations).
"""

from __future__ import annotations

import os
from dataclasses import dataclass
from typing import Any

from ebrl.config import vectorized
from ebrl.presets import PRESETS



@dataclass(frozen=True)
class Schedule:
    mode: str
    groups: int  # groups as scheduled (1 when group pipelining is off)
    envs_per_group: int
    stepping: str  # "async" | "batch"
    core_rebinding: bool  # env workers claim cores from a shared pool (rebinding, or pinned chunks under auto)
    overlap: bool
    max_staleness: int  # 0 when overlap is off: every decision of iteration i comes from policy version i
    rollout_length: int  # decisions per env per iteration, with one sim host (see ``length``)
    sim_cores: list[int]
    gen_cores: list[int]  # empty: not pinned
    train_cores: list[int]  # empty: not pinned
    # False for episodic algorithms (GRPO): a group must finish whole episodes before training can use them,
    # which a fixed decision budget per iteration cannot promise, so generation is never held back by
    # iteration; the staleness bound is kept by training alone (older decisions are dropped, counted).
    throttle: bool = True
    # sim.core_rebinding = "auto": rebinding or pinned whole chunks, whichever measures faster (stepchoice)
    rebinding_auto: bool = False
    # sim.vectorized: each group one process stepping its envs as a batch (no per-env stepping, no rebinding)
    vectorized: bool = False
    # sim.cores_per_env: each env worker pinned to a set of this many cores (a multi-threaded simulator); above 1
    # there is no step-level rebinding, which hands out single cores
    cores_per_env: int = 1
    # sim.lazy_render: envs that render on demand render only the observations the policy reads
    lazy_render: bool = True
    # sim.nice: the niceness each env worker and vectorized group process takes before it starts
    nice: int = 0

    def length(self, hosts: int = 1) -> int:
        """Decisions per env per iteration while ``hosts`` sim hosts are live: an update's batch comes from all
        of them. Counted live, not configured, so a host that leaves never leaves the others waiting for
        decisions it would have made (when the count changes, the iteration a seq maps to jumps once)."""
        return max(1, self.rollout_length // max(1, hosts))

    def iteration_of(self, seq: int, hosts: int = 1) -> int:
        """The iteration a group's chunk ``seq`` belongs to."""
        return seq // self.length(hosts)

    def min_version(self, seq: int, hosts: int = 1) -> int:
        """Oldest policy version allowed to answer chunk ``seq``: iteration i may be acted by version
        i - max_staleness or newer, so the update that learns from it is at most max_staleness ahead."""
        if not self.throttle:
            return -1
        return self.iteration_of(seq, hosts) - self.max_staleness


def available_cores() -> list[int]:
    return sorted(os.sched_getaffinity(0))


def resolve(cfg: Any, cores: list[int] | None = None) -> Schedule:
    """The schedule of ``cfg`` on a machine whose usable cores are ``cores`` (default: this process's)."""
    preset = PRESETS[cfg.run.mode]
    cores = list(cores) if cores is not None else available_cores()

    def pick(value: Any, name: str) -> Any:
        return preset[name] if value is None else value

    group_pipeline = pick(cfg.sim.group_pipeline, "group_pipeline")
    batched = vectorized(cfg)
    stepping = "batch" if batched else pick(cfg.sim.stepping, "stepping")  # a vectorized batch steps as one
    rebinding = pick(cfg.sim.core_rebinding, "core_rebinding")
    core_rebinding = bool(rebinding) and stepping == "async" and cfg.sim.cores_per_env == 1
    overlap = pick(cfg.train.overlap, "overlap")
    sim_cores, gen_cores, train_cores = list(cfg.sim.cores), list(cfg.gen.cores), list(cfg.train.cores)
    if preset["disjoint"] and not (sim_cores or gen_cores or train_cores):
        # Async disaggregated systems give rollout and training separate hardware: split the cores.
        half = max(1, len(cores) // 2)
        rollout, train = (cores[:half], cores[half:]) if len(cores) > 1 else (cores, cores)
        sim_cores, gen_cores, train_cores = rollout, rollout, train
    groups = cfg.sim.groups if group_pipeline else 1
    return Schedule(
        mode=cfg.run.mode,
        groups=groups,
        envs_per_group=cfg.num_envs // groups,
        stepping=stepping,
        core_rebinding=core_rebinding,
        overlap=overlap,
        max_staleness=cfg.algo.max_staleness if overlap else 0,
        rollout_length=cfg.rollout_length,
        sim_cores=sim_cores or cores,
        gen_cores=gen_cores,
        train_cores=train_cores,
        throttle=cfg.algo.name != "grpo" and cfg.algo.keep_utd,
        rebinding_auto=core_rebinding and rebinding == "auto",
        vectorized=batched,
        cores_per_env=cfg.sim.cores_per_env,
        lazy_render=bool(pick(cfg.sim.lazy_render, "lazy_render")),
        nice=cfg.sim.nice,
    )


def home_cores(cores: list[int], cores_per_env: int, i: int) -> int | tuple[int, ...]:
    """Where env ``i`` is statically pinned: core ``i mod len(cores)``, or with ``cores_per_env`` = c > 1 the
    ``i mod E``-th of the E = len(cores) // c disjoint sets of c cores (all of them when they are fewer than c)."""
    if cores_per_env <= 1:
        return cores[i % len(cores)]
    sets = max(1, len(cores) // cores_per_env)
    if sets == 1:
        return tuple(cores[:cores_per_env])
    j = i % sets
    return tuple(cores[j * cores_per_env:(j + 1) * cores_per_env])
