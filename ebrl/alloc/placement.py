"""``EmbodiPlacement``: the programming API of the allocator (the paper's listing), runnable on CPU.

    pool = ResourcePool(gpu_pool="none")
    prof = profile(pool, cfg)                       # or load_or_profile(...)
    placement = EmbodiPlacement(pool=pool, profile=prof)
    placement.apply()                               # initial plan: bindings in the pool
    for it in range(iters):
        placement.balance(rates).apply()           # re-plans only after a sustained imbalance

* The initial plan is Algorithm 1 (:mod:`ebrl.alloc.algorithm`): on a GPU
  machine SM quotas, on a CPU-only one cores (``allocate_cpu``; a machine with
  fewer cores than simulator + generation + training lets generation and
  training time-share their cores), compared with not partitioning at all
  (:func:`all_shared`); the higher predicted Theta wins.
* ``balance(rates)`` takes one observation of the stages' measured capacities
  (decisions per second) and keeps ``window``-long moving averages of rollout
  (``min(sim, gen)``) and training. When they differ by more than ``gap`` of the
  faster one for ``patience`` consecutive observations, it refines the tables
  with the measurements (``refine``) and reruns Algorithm 1; a different plan
  becomes pending, and ``apply()`` binds it (and hands it to ``on_apply``, which
  the allocator service uses to push affinities and quotas to the services).
* A re-plan is a trial: profiles taken alone misjudge stages that share a
  machine, so after ``window`` observations the end-to-end rate it achieved is
  compared with the previous plan's; if it is worse, the previous plan comes
  back and the tried one is excluded for a while.
"""

from __future__ import annotations

import collections
import dataclasses
import math
from typing import Callable

from ebrl.alloc.algorithm import (Allocation, InfeasibleError, Profiles, allocate, allocate_cpu, choose_c_env,
                                  refine)
from ebrl.resources.pool import ResourcePool, WorkerResourceBinding


@dataclasses.dataclass
class StageRates:
    """Measured capacity of each stage (decisions/s it could sustain while busy), one observation."""

    sim: float
    gen: float
    train: float
    achieved: float = 0.0  # end-to-end decisions/s actually reached (0: unknown); judges a re-plan
    remote_sim: float = 0.0  # the part of ``sim`` that other hosts simulate

    @property
    def rollout(self) -> float:
        return min(self.sim, self.gen)


@dataclasses.dataclass
class Plan:
    """A concrete allocation: cores and threads per stage, batch sizes, what Algorithm 1 predicted."""

    version: int
    allocation: Allocation
    cores: dict[str, list[int]]
    threads: dict[str, int]
    gen_batch: int
    train_batch: int
    reason: str

    @property
    def signature(self) -> tuple:
        return tuple((stage, tuple(cores)) for stage, cores in sorted(self.cores.items())) + (self.gen_batch,)

    def same_resources(self, other: "Plan | None") -> bool:
        return other is not None and self.signature == other.signature


def all_shared(profiles: Profiles, n: int, remote_sim: float = 0.0, local_sim: bool = True) -> Allocation:
    """The CPU-only alternative to partitioning: every stage on all ``n`` cores, time-sharing them.

    Each decision then costs the cores 1/P_sim + 1/P_gen + 1/P_train seconds (every stage measured alone
    on all n cores), so Theta is the harmonic combination. T_sim, T_gen, T_train keep the stand-alone rates,
    which is what measured capacities (rate while busy) are compared against when the tables are refined.
    Sharing wins when no stage dominates; partitioning wins when one stage would crowd out the others.

    With simulation on other hosts (``remote_sim`` decisions/s), their decisions cost these cores only
    1/P_gen + 1/P_train: they are taken first, and the time left simulates here (none if not ``local_sim``).
    """
    c_env, E = choose_c_env(profiles, n) if local_sim and profiles.sim else (1, 0)  # line 1, on every core
    T_sim = profiles.P_sim(c_env, E, c_env * E) if E else 0.0
    B_g = max(profiles._gen_curves, key=lambda b: profiles.P_gen(n, b))
    B_t = max(profiles._train_curves, key=lambda b: profiles.P_train(n, b))
    T_gen, T_train = profiles.P_gen(n, B_g), profiles.P_train(n, B_t)
    theta_ = 0.0
    if T_gen > 0 and T_train > 0:
        model = 1.0 / T_gen + 1.0 / T_train  # core-seconds per decision of generation and training
        remote = min(remote_sim, 1.0 / model)
        left = 1.0 - remote * model  # of each second of the cores
        theta_ = remote + (left / (model + 1.0 / T_sim) if T_sim > 0 else 0.0)
    return Allocation(c_env=c_env if E else 0, E=E, s_sim=n if E else 0, s_gen=n, s_train=n, B_gen=B_g, B_train=B_t,
                      T_sim=T_sim + remote_sim, T_gen=T_gen, T_train=T_train, theta=theta_, evaluations=1,
                      method="all_shared")


TRIAL_TOLERANCE = 0.05  # a re-plan that achieves more than 5 % less than the plan before is reverted
REJECT_FOR = 10  # ... and its plan is not chosen again for REJECT_FOR x patience observations


class EmbodiPlacement:
    """The elastic allocator as a library: Algorithm 1's plan for ``pool`` from the stage tables ``profile``,
    re-planned from measured capacities.

    ``apply()`` binds the pending plan in the pool (and hands it to ``on_apply``); ``balance(rates)`` takes one
    :class:`StageRates` observation and, when rollout and training capacity (``window``-long moving averages)
    differ by more than ``gap`` of the faster for ``patience`` observations in a row, refines the tables with
    the measurements and makes a new pending plan, a trial that is undone if it achieves less. ``plan`` is the
    pending plan, else the applied one::

        pool = ResourcePool(gpu_pool="none")
        placement = EmbodiPlacement(pool, profile(pool, cfg))  # or a stored table: load_or_profile
        placement.apply()
        placement.balance(StageRates(sim=900.0, gen=2400.0, train=450.0)).apply()
    """

    def __init__(self, pool: ResourcePool, profile: Profiles, *, window: int = 20, gap: float = 0.15,
                 patience: int = 20, s_g_min: int = 1, s_t_min: int = 1,
                 on_apply: Callable[[Plan], None] | None = None, local_sim: bool = True, remote_sim: float = 0.0):
        """``local_sim = False``: this host only generates and trains (the simulators run on other hosts).
        ``remote_sim``: the other hosts' simulation capacity in decisions/s, as far as known; ``balance``
        keeps it up to date from their stats. Unknown and without local simulation, it is taken as no limit."""
        self.pool, self.profiles = pool, profile
        self.local_sim = local_sim
        self.remote_sim = remote_sim if local_sim or remote_sim > 0 else math.inf
        self.window, self.gap, self.patience = window, gap, patience
        self.s_g_min, self.s_t_min = s_g_min, s_t_min
        self.on_apply = on_apply
        self.rollout: collections.deque[float] = collections.deque(maxlen=window)
        self.train: collections.deque[float] = collections.deque(maxlen=window)
        self.imbalanced = 0  # consecutive observations over the gap
        self.achieved: collections.deque[float] = collections.deque(maxlen=window)
        self.remote: collections.deque[float] = collections.deque(maxlen=window)  # other hosts' simulation
        self.trial: tuple[Plan, float] | None = None  # (plan before the re-plan, its achieved rate)
        self.rejected: dict[tuple, int] = {}  # plan signature -> observations it stays excluded
        self.history: list[Plan] = []
        self.applied: Plan | None = None
        self.pending: Plan | None = self._plan(self._allocate(profile), "initial allocation")
        # cores per env stay what the run starts with (Algorithm 1's line 1 on the profile): the env workers are
        # pinned by it, and it is a property of the simulator, not of the balance between stages
        if self.pending.allocation.c_env:
            self.profiles = self.profiles.with_c_env(self.pending.allocation.c_env)

    # --- Algorithm 1 -> a concrete plan --------------------------------------------------------

    def _allocate(self, profiles: Profiles) -> Allocation:
        n = len(self.pool.cores)
        if self.pool.gpus and self.pool.gpu_pool != "none":
            # scan_sim: the paper's knee-first line 3 reached only 0.59-0.75 of the optimum on some tables
            # (benchmarks/allocator_quality.py); scanning the simulator quota reaches it everywhere
            return allocate(profiles, N=n, s_g_min=self.s_g_min, s_t_min=self.s_t_min, scan_sim=True)
        # too few cores to pin gen and train apart (and the simulator, when it runs here)
        shared = 1 if n < self.s_g_min + self.s_t_min + self.local_sim else None
        candidates = [all_shared(profiles, n, self.remote_sim, self.local_sim)]
        try:
            candidates.append(allocate_cpu(profiles, N=n, s_g_min=self.s_g_min, s_t_min=self.s_t_min,
                                           shared_model_cores=shared, remote_sim=self.remote_sim,
                                           local_sim=self.local_sim))
        except InfeasibleError:
            pass
        allowed = [a for a in candidates if self._plan(a, "").signature not in self.rejected] or candidates
        best = max(allowed, key=lambda a: a.theta)
        if best.theta <= 0:
            raise InfeasibleError(f"no allocation of {n} cores gives every stage a profiled rate "
                                  f"(pool: {self.pool.describe()})")
        return best

    def _plan(self, alloc: Allocation, reason: str) -> Plan:
        cores = self.pool.core_ids
        if alloc.method == "all_shared":  # no partition: every stage may run on every core
            split = {"sim": cores if alloc.E else [], "gen": cores, "train": cores}
        elif alloc.method == "shared":  # gen and train time-share the cores the simulator leaves
            sim = cores[:alloc.s_sim]
            model = cores[alloc.s_sim:alloc.s_sim + alloc.s_gen]
            split = {"sim": sim, "gen": model, "train": model}
        elif self.pool.gpus and self.pool.gpu_pool != "none":  # GPU quotas; CPU cores all to the simulator
            split = {"sim": cores, "gen": cores[:1], "train": cores[-1:]}
        else:
            split = self.pool.partition({"sim": alloc.s_sim, "gen": alloc.s_gen, "train": alloc.s_train})
        threads = {stage: max(1, len(c)) for stage, c in split.items()}
        version = (self.history[-1].version + 1) if self.history else 1
        return Plan(version, alloc, split, threads, alloc.B_gen, alloc.B_train, reason)

    # --- the API -----------------------------------------------------------------------------

    @property
    def plan(self) -> Plan:
        return self.pending or self.applied  # type: ignore[return-value]

    def apply(self) -> "EmbodiPlacement":
        """Bind the pending plan (if any) in the pool and hand it to ``on_apply``; no-op otherwise."""
        plan, self.pending = self.pending, None
        if plan is None:
            return self
        if self.applied is not None and not plan.reason.startswith("reverted"):
            # A re-plan is a trial: judged against what the previous plan really achieved.
            baseline = sum(self.achieved) / len(self.achieved) if self.achieved else 0.0
            self.trial = (self.applied, baseline) if baseline > 0 else None
        self.achieved.clear()
        gpu = 0 if self.pool.gpus and self.pool.gpu_pool != "none" else None
        if gpu is not None and self.pool.gpu_pool == "mps":
            # the new shares replace the old ones whole (one at a time they could add up to over 100 %);
            # each stage's memory budget is its share of the GPU's memory, like its SMs
            self.pool.clear_quotas(gpu)
            alloc, memory = plan.allocation, self.pool.gpus[gpu].memory_bytes
            for stage, share in (("sim", alloc.s_sim), ("gen", alloc.s_gen), ("train", alloc.s_train)):
                if share > 0:
                    self.pool.set_quota(stage, gpu, share, mem_bytes=memory * share // 100)
        for stage in ("sim", "gen", "train"):
            if plan.cores[stage]:  # no simulator on a host whose simulation runs elsewhere
                # generation and training work on the GPU: their binding's env carries its share (MPS) or
                # instance (MIG), which the launcher starts them with
                self.pool.bind(f"{stage}/0", stage, plan.cores[stage], threads=plan.threads[stage],
                               gpu=gpu if stage != "sim" else None)
        self.applied = plan
        self.history.append(plan)
        if self.on_apply is not None:
            self.on_apply(plan)
        return self

    def bindings(self) -> dict[str, WorkerResourceBinding]:
        return dict(self.pool.bindings)

    def balance(self, rates: StageRates) -> "EmbodiPlacement":
        """One observation of measured stage capacities; re-plan after a sustained imbalance."""
        if not all(math.isfinite(x) and x > 0 for x in (rates.sim, rates.gen, rates.train)):
            return self  # a stage that did nothing in this interval tells nothing about its capacity
        self.rejected = {sig: left - 1 for sig, left in self.rejected.items() if left > 1}
        self.remote.append(rates.remote_sim)
        self.remote_sim = sum(self.remote) / len(self.remote)
        if rates.achieved > 0:
            self.achieved.append(rates.achieved)
        if self.trial is not None:
            return self._judge_trial()
        self.rollout.append(rates.rollout)
        self.train.append(rates.train)
        if len(self.rollout) < self.window:
            return self
        rollout, train = sum(self.rollout) / len(self.rollout), sum(self.train) / len(self.train)
        if abs(rollout - train) > self.gap * max(rollout, train):
            self.imbalanced += 1
        else:
            self.imbalanced = 0
        if self.imbalanced < self.patience:
            return self
        self.imbalanced = 0
        current = (self.applied or self.pending).allocation  # type: ignore[union-attr]
        # what the plan predicts with the other hosts' simulation as it is now: a host that came or went is
        # no misprediction of this host's tables
        here = self.profiles.P_sim(current.c_env, current.E, current.s_sim) if current.E else 0.0
        current = dataclasses.replace(current, T_sim=here + self.remote_sim)
        self.profiles = refine(self.profiles, current, rollout, train)
        plan = self._plan(self._allocate(self.profiles),
                          f"rollout {rollout:,.0f} vs training {train:,.0f} decisions/s for {self.patience} reports")
        if not plan.same_resources(self.applied):
            self.pending = plan
        self.rollout.clear()
        self.train.clear()
        return self

    def _judge_trial(self) -> "EmbodiPlacement":
        """After a re-plan, wait ``window`` observations; keep the plan unless it achieved less than the one
        before (by more than TRIAL_TOLERANCE), else go back and exclude the tried plan for a while."""
        previous, baseline = self.trial  # type: ignore[misc]
        if len(self.achieved) < self.window:
            return self
        now = sum(self.achieved) / len(self.achieved)
        self.trial = None
        if now >= (1 - TRIAL_TOLERANCE) * baseline:
            return self
        tried: Plan = self.applied  # type: ignore[assignment]
        self.rejected[tried.signature] = REJECT_FOR * self.patience
        reason = (f"reverted: plan v{tried.version} achieved {now:,.0f} decisions/s, "
                  f"v{previous.version} {baseline:,.0f}")
        self.pending = dataclasses.replace(previous, version=self.history[-1].version + 1, reason=reason)
        self.rollout.clear()
        self.train.clear()
        return self
