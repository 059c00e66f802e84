"""``ebrl profile CONFIG``: measure (or reuse) the stage tables and show what Algorithm 1 makes of them."""

from __future__ import annotations

import sys
from pathlib import Path

from ebrl import config as config_mod
from ebrl.alloc.algorithm import InfeasibleError
from ebrl.alloc.placement import EmbodiPlacement
from ebrl.alloc.profile import load_or_profile
from ebrl.resources.pool import ResourceError, ResourcePool


def profile_command(config_path: str, overrides: list[str], force: bool = False, seconds: float | None = None,
                    out: str | None = None) -> int:
    try:
        cfg = config_mod.load(config_path, overrides)
        pool = ResourcePool(gpu_pool=cfg.alloc.gpu_pool, cpu_pool=cfg.alloc.cpu_pool)
    except (config_mod.ConfigError, ResourceError) as exc:
        print(f"ebrl: {exc}", file=sys.stderr)
        return 2
    print(f"pool: {pool.describe()}")
    profiles, path, measured = load_or_profile(pool, cfg, Path(out) if out else None, force=force,
                                               seconds=seconds or cfg.alloc.profile_seconds)
    print(f"{'measured' if measured else 'reused'} {path}")
    print(format_tables(profiles))
    try:
        plan = EmbodiPlacement(pool, profiles, s_g_min=cfg.alloc.min_gen_cores, s_t_min=cfg.alloc.min_train_cores).plan
    except InfeasibleError as exc:
        print(f"Algorithm 1: no feasible allocation: {exc}")
        return 1
    a = plan.allocation
    print(f"Algorithm 1 ({a.method}, {a.evaluations} evaluations): sim {a.s_sim} ({a.E} envs at once, "
          f"{a.c_env} core{'s' if a.c_env != 1 else ''} each), "
          f"gen {a.s_gen}, train {a.s_train}; batches gen {a.B_gen}, train {a.B_train}")
    print(f"  predicted decisions/s: sim {a.T_sim:,.0f}, gen {a.T_gen:,.0f}, train {a.T_train:,.0f} -> "
          f"Theta {a.theta:,.0f}")
    print("  cores: " + ", ".join(f"{stage} {cores}" for stage, cores in plan.cores.items()))
    return 0


def format_tables(profiles) -> str:
    lines = []
    if profiles.sim_cores_used is not None:
        lines.append(f"one env keeps {profiles.sim_cores_used:.2f} cores busy while it steps (sim/env_cores_used)")
    lines.append("P_sim  (c_env, E, quota) -> decisions/s")
    lines += [f"  {key}: {rate:,.0f}" for key, rate in sorted(profiles.sim.items())]
    lines.append("P_gen  (quota, batch) -> decisions/s")
    lines += [f"  {key}: {rate:,.0f}" for key, rate in sorted(profiles.gen.items())]
    lines.append("P_train (quota, batch) -> decisions/s")
    lines += [f"  {key}: {rate:,.0f}" for key, rate in sorted(profiles.train.items())]
    return "\n".join(lines)
