"""The allocator at run time: the initial plan before services start, then measured capacities -> re-plans.

* :func:`initial_config` (the launcher, before spawning): the pool, the stage
  profile (reused or measured), Algorithm 1's plan, written into the resolved
  config (``sim.cores``, ``gen.cores``/``threads``/``max_batch_groups``,
  ``train.cores``/``threads``) so every service starts inside its share.
* :func:`capacities` (the allocator service, every stats report): what each
  stage could sustain on its cores, in decisions/s, from the services' stats
  (decisions per CPU-second times its cores).
* :func:`gpu_shares` (the allocator service, after a re-plan): the GPU share
  each stage's processes must start again with, for the launcher of its host.
"""

from __future__ import annotations

import dataclasses
import math
from pathlib import Path
from typing import Any

from ebrl import config as config_mod
from ebrl.alloc.placement import EmbodiPlacement, Plan, StageRates
from ebrl.alloc.profile import default_path, fingerprint, load, load_or_profile
from ebrl.messages import Affinity, GpuShare, Quota
from ebrl.resources.pool import ResourcePool

MIN_CPU = 0.05  # cores' worth of CPU below which a stage was idle: its capacity cannot be told


def make_placement(cfg: config_mod.Config, *, measure: bool, progress: bool = True,
                   local_sim: bool = True) -> tuple[EmbodiPlacement, Path, bool]:
    """The pool, profile (measured only if ``measure`` and nothing fresh is stored) and placement of ``cfg``;
    ``local_sim = False`` for a host whose simulators run elsewhere."""
    pool = ResourcePool(gpu_pool=cfg.alloc.gpu_pool, cpu_pool=cfg.alloc.cpu_pool)
    path = Path(cfg.alloc.profile_path) if cfg.alloc.profile_path else default_path(cfg)
    if measure:
        profiles, path, measured = load_or_profile(pool, cfg, path, seconds=cfg.alloc.profile_seconds,
                                                   progress=progress)
    else:  # the allocator service: the launcher profiled just now; never measure while the run goes on
        stored, measured = load(path, fingerprint(pool, cfg), math.inf), False
        if stored is None:
            raise FileNotFoundError(f"no stage profile of this machine and workload at {path}")
        profiles = stored
    if cfg.sim.core_rebinding is True:  # rebinding single steps, as the user asked: one core per env
        profiles = profiles.with_c_env(1)
    placement = EmbodiPlacement(pool, profiles, window=cfg.alloc.window, gap=cfg.alloc.gap,
                                patience=cfg.alloc.patience, s_g_min=cfg.alloc.min_gen_cores,
                                s_t_min=cfg.alloc.min_train_cores, local_sim=local_sim)
    return placement, path, measured


def initial_config(cfg: config_mod.Config, local_sim: bool = True
                   ) -> tuple[config_mod.Config, dict[str, dict[str, str]], str]:
    """``cfg`` with the initial plan's cores, threads and batch written in; the GPU environment each stage
    starts with (``gpu_env``); a line for the user."""
    placement, path, measured = make_placement(cfg, measure=True, local_sim=local_sim)
    plan = placement.apply().applied
    per = cfg.sim.envs_per_group
    new = dataclasses.replace(
        cfg,
        sim=dataclasses.replace(cfg.sim, cores=plan.cores["sim"],
                                cores_per_env=plan.allocation.c_env or cfg.sim.cores_per_env),
        gen=dataclasses.replace(cfg.gen, cores=plan.cores["gen"], threads=plan.threads["gen"],
                                max_batch_groups=max(1, plan.gen_batch // per)),
        train=dataclasses.replace(cfg.train, cores=plan.cores["train"], threads=plan.threads["train"]),
        alloc=dataclasses.replace(cfg.alloc, profile_path=str(path)),
    )
    return new, gpu_env(placement), f"allocator: {'profiled' if measured else 'reused profile'} {path}; " \
                                    f"{describe(plan)}"


def gpu_env(placement: EmbodiPlacement) -> dict[str, dict[str, str]]:
    """Stage -> the CUDA variables of its binding (device, MPS share, MIG instance); empty without a GPU."""
    return {binding.stage: {k: v for k, v in binding.env.items() if k.startswith("CUDA_")}
            for binding in placement.bindings().values() if binding.gpu is not None}


def gpu_shares(placement: EmbodiPlacement) -> list[GpuShare]:
    """The applied plan's GPU share of each stage, for the launcher of the allocator's host: MPS fixes a share
    when a process makes its CUDA context, so a new one takes a new process (empty without a GPU)."""
    version = placement.applied.version
    return [GpuShare(version=version, stage=stage, env=env) for stage, env in gpu_env(placement).items()]


def describe(plan: Plan) -> str:
    a = plan.allocation
    return (f"plan v{plan.version} ({a.method}): " + ", ".join(f"{s} cores {c}" for s, c in plan.cores.items())
            + (f" ({a.c_env} per env)" if a.c_env > 1 else "")
            + f", gen batch {plan.gen_batch}; predicted {a.theta:,.0f} decisions/s")


def capacities(sim: dict[str, float] | None, gen: dict[str, float], train: dict[str, float], *, chunk: int,
               cores: dict[str, int], batch_size: int, remote: list[dict[str, float]] = ()) -> StageRates | None:
    """Measured stage capacities from one stats report of each service, or None when a stage did too little
    in the interval to tell.

    A stage's capacity is its decisions per CPU-second times the cores its plan gives it: CPU time, not
    wall-clock busy time, so that stages time-sharing cores are not charged for each other's turns, and
    the numbers compare with the profiles (each stage measured alone on its cores). Simulation counts the
    env workers' CPU inside steps; generation and training their processes' CPU.

    Several hosts: ``sim`` is this host's simulator (None if it has none) and ``remote`` the latest reports
    of the others; each counts with its own cores (``sim/cores``), and their sum is ``remote_sim``.
    """
    gen_rate, gen_cpu = gen.get("gen/envs_served_per_s", 0.0), gen.get("proc/cpu_percent", 0.0) / 100
    train_rate = train.get("train/updates_per_s", 0.0) * batch_size
    train_cpu = train.get("proc/cpu_percent", 0.0) / 100
    if min(gen_cpu, train_cpu) < MIN_CPU or min(gen_rate, train_rate) <= 0:
        return None
    local = achieved = 0.0
    if sim is not None:
        sim_rate, sim_cpu = sim.get("sim/env_steps_per_s", 0.0) / chunk, sim.get("sim/step_busy_s_per_s", 0.0)
        if sim_cpu < MIN_CPU or sim_rate <= 0:
            return None
        local, achieved = sim_rate / sim_cpu * cores["sim"], sim_rate
    remote_sim = 0.0
    for other in remote:
        rate, cpu = other.get("sim/env_steps_per_s", 0.0) / chunk, other.get("sim/step_busy_s_per_s", 0.0)
        # a host whose simulator barely ran cannot tell its capacity: count what it did
        remote_sim += rate / cpu * other["sim/cores"] if cpu >= MIN_CPU and other.get("sim/cores") else rate
        achieved += rate
    if local + remote_sim <= 0:
        return None
    return StageRates(sim=local + remote_sim, gen=gen_rate / gen_cpu * cores["gen"],
                      train=train_rate / train_cpu * cores["train"], achieved=achieved, remote_sim=remote_sim)


def metrics_of(placement: EmbodiPlacement, rates: StageRates | None) -> dict[str, Any]:
    plan = placement.applied
    out: dict[str, float] = {"alloc/plan_version": float(plan.version) if plan else 0.0,
                             "alloc/imbalanced_reports": float(placement.imbalanced)}
    if plan is not None:
        out["alloc/theta_predicted"] = plan.allocation.theta
        out["alloc/cores_per_env"] = float(plan.allocation.c_env)
        for stage, cores in plan.cores.items():
            out[f"alloc/cores_{stage}"] = float(len(cores))
    if rates is not None:
        out.update({"alloc/sim_capacity": rates.sim, "alloc/gen_capacity": rates.gen,
                    "alloc/train_capacity": rates.train, "alloc/remote_sim_capacity": rates.remote_sim})
    if placement.rollout:
        rollout = sum(placement.rollout) / len(placement.rollout)
        train = sum(placement.train) / len(placement.train)
        out.update({"alloc/rollout_avg": rollout, "alloc/train_avg": train,
                    "alloc/gap": abs(rollout - train) / max(rollout, train)})
    return out


REMOTE_STALE_REPORTS = 3  # a host's simulator stats older than this many intervals no longer count (it left)


class Observations:
    """The newest stats of each stage, as the allocator reads them: gen's and train's, and every sim host's
    with the time it came (a host that stops reporting for ``REMOTE_STALE_REPORTS`` intervals has left)."""

    def __init__(self, host: int, local_sim: bool, stats_interval: float):
        self.host, self.local_sim, self.stale_s = str(host), local_sim, REMOTE_STALE_REPORTS * stats_interval
        self.latest: dict[str, dict[str, float]] = {}
        self.sims: dict[str, tuple[float, dict[str, float]]] = {}  # sim instance -> (received at, metrics)

    def stage(self, role: str, metrics: dict[str, float]) -> None:
        self.latest[role] = metrics

    def sim(self, instance: str, metrics: dict[str, float], now: float) -> None:
        self.sims[instance] = (now, metrics)

    def ready(self, now: float) -> bool:
        """Forget the hosts that left; True once every report the capacities need is here."""
        self.sims = {i: (t, m) for i, (t, m) in self.sims.items() if now - t <= self.stale_s}
        return "gen" in self.latest and "train" in self.latest and (not self.local_sim or self.host in self.sims)

    def rates(self, plan: Plan, chunk: int, batch_size: int) -> StageRates | None:
        """Each stage's capacity under ``plan`` (``capacities``; None where it cannot be told yet)."""
        local = self.sims.get(self.host)
        remote = [m for i, (_, m) in self.sims.items() if i != self.host]
        return capacities(local[1] if self.local_sim else None, self.latest["gen"], self.latest["train"],
                          chunk=chunk, batch_size=batch_size, cores={st: len(c) for st, c in plan.cores.items()},
                          remote=remote)


def plan_messages(placement: EmbodiPlacement, host: int, local_sim: bool) -> list[tuple[str, int, Any]]:
    """What the applied plan tells each stage: ``(stage, instance, message)`` — its cores (``Affinity``) and, for
    gen and train, threads, batch and GPU share (``Quota``; a new share takes a new process: ``gpu_shares``)."""
    plan, out = placement.applied, []
    for stage in ("sim", "gen", "train"):
        if stage == "sim" and not local_sim:
            continue
        instance = host if stage == "sim" else 0
        out.append((stage, instance, Affinity(version=plan.version, cores=plan.cores[stage])))
        if stage != "sim":
            binding = placement.bindings().get(f"{stage}/0")
            out.append((stage, 0, Quota(version=plan.version, threads=plan.threads[stage],
                                        sm_percent=binding.sm_percent if binding else None,
                                        mem_bytes=binding.mem_bytes if binding else None,
                                        batch=plan.gen_batch if stage == "gen" else None)))
    return out

