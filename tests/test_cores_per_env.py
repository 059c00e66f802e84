"""Cores per environment: how many cores an env keeps busy while it steps (``cores_used``, measured by the env
workers), the pinning of every thread of a worker to its own cores (``sim.cores_per_env``), the stepping choice
that does not rebind multi-threaded envs, and the allocator's profile and plan that pick cores per env from the
same measurement. Real worker processes; the allocator's tables are synthetic where a test is about its choice."""

from __future__ import annotations

import asyncio
import dataclasses
import math
import os
from pathlib import Path

import numpy as np
import pytest

from ebrl import config
from ebrl.alloc import profile as profile_mod
from ebrl.alloc.algorithm import Profiles
from ebrl.alloc.placement import EmbodiPlacement, StageRates
from ebrl.envs import EnvSpec, EnvWorker
from ebrl.envs.worker import ChunkResult, cores_used
from ebrl.resources.pool import Core, ResourcePool
from ebrl.resources.corepool import PINNED, REBIND
from ebrl.sched.fleet import EnvFleet
from ebrl.sched.modes import home_cores, resolve
from ebrl.sched.stepchoice import SteppingChoice

CORES = sorted(os.sched_getaffinity(0))
THREADED = EnvSpec("user_envs:ThreadedStep-v0")  # steps on two threads (tests/user_envs.py)
SINGLE = EnvSpec("Pendulum-v1", latency="lognormal", latency_mean_ms=1.0, latency_sigma=0.0)
two_cores = pytest.mark.skipif(len(CORES) < 2, reason="needs 2 cores to pin to different ones")


def threads_affinity(pid: int) -> list[set[int]]:
    return [os.sched_getaffinity(int(tid)) for tid in os.listdir(f"/proc/{pid}/task")]


def run_chunks(worker: EnvWorker, count: int, k: int = 4) -> list[ChunkResult]:
    async def go():
        await worker.reset()
        return [await worker.chunk(np.zeros((k, 1), np.float32)) for _ in range(count)]

    return asyncio.run(go())


# --- the measurement -----------------------------------------------------------------------------------------


def test_cores_used_is_every_threads_step_cpu_over_step_wall():
    def result(step_s, step_cpu_s, helper):
        return ChunkResult(0.0, len(step_s), False, False, np.zeros(1), np.zeros(1), None, None,
                           step_s=step_s, step_cpu_s=step_cpu_s, helper_cpu_s=helper)

    assert cores_used([result((0.01, 0.01), (0.01, 0.008), 0.0)]) == pytest.approx(0.9)
    assert cores_used([result((0.01,), (0.01,), 0.01), result((0.01,), (0.01,), 0.02)]) == pytest.approx(2.5)
    assert math.isnan(cores_used([]))


def test_a_worker_counts_its_simulators_own_threads():
    threaded, single = EnvWorker(THREADED, seed=0), EnvWorker(SINGLE, seed=0)
    try:
        many, one = run_chunks(threaded, 10), run_chunks(single, 10)
    finally:
        threaded.close()
        single.close()
    # CPU time, not parallelism: these hold however loaded the machine is
    step_cpu = sum(sum(r.step_cpu_s) for r in many)
    assert sum(r.helper_cpu_s for r in many) > 0.3 * step_cpu  # the helper hashes as much as the stepping thread
    assert sum(r.helper_cpu_s for r in one) < 0.02 * sum(sum(r.step_cpu_s) for r in one)
    assert cores_used(one) <= 1.05  # one thread cannot keep more than one core busy


@two_cores
def test_pinning_a_worker_moves_every_thread_of_it():
    worker = EnvWorker(THREADED, seed=0, core=CORES[0])
    try:
        run_chunks(worker, 1)  # the env (and its helper thread) exists
        assert len(threads_affinity(worker.proc.pid)) >= 2
        assert all(a == {CORES[0]} for a in threads_affinity(worker.proc.pid))  # pinned before the env started it
        worker.pin(CORES[1])
        assert all(a == {CORES[1]} for a in threads_affinity(worker.proc.pid)) and worker.home == (CORES[1],)
        worker.pin(tuple(CORES[:2]))
        assert all(a == set(CORES[:2]) for a in threads_affinity(worker.proc.pid))
        assert run_chunks(worker, 1)[0].steps == 4
    finally:
        worker.close()


def test_home_cores_are_disjoint_sets_of_cores_per_env():
    cores = [0, 1, 2, 3, 4]
    assert [home_cores(cores, 1, i) for i in range(6)] == [0, 1, 2, 3, 4, 0]
    assert [home_cores(cores, 2, i) for i in range(3)] == [(0, 1), (2, 3), (0, 1)]  # core 4 stays unused
    assert home_cores(cores, 8, 3) == (0, 1, 2, 3, 4)  # fewer cores than one env wants: all of them
    assert home_cores([7], 2, 0) == (7,)


# --- the config and the schedule ------------------------------------------------------------------------------


def test_cores_per_env_turns_rebinding_off_and_is_checked():
    cfg = config.from_dict({"sim": {"cores_per_env": 2}})  # the ebrl mode: core_rebinding "auto"
    schedule = resolve(cfg, cores=[0, 1, 2, 3])
    assert schedule.cores_per_env == 2 and not schedule.core_rebinding and not schedule.rebinding_auto
    with pytest.raises(config.ConfigError, match="sim.cores_per_env = 2.*sim.core_rebinding = true"):
        config.from_dict({"sim": {"cores_per_env": 2, "core_rebinding": True}})
    with pytest.raises(config.ConfigError, match="sim.cores_per_env"):
        config.from_dict({"sim": {"cores_per_env": 0}})


@two_cores
def test_a_fleet_pins_each_env_worker_to_its_own_set_of_cores():
    cfg = config.from_dict({"env": {"id": THREADED.id}, "sim": {"groups": 1, "envs_per_group": 2,
                                                                 "cores_per_env": 2, "cores": CORES[:2]},
                            "train": {"batch_size": 64}})
    fleet = EnvFleet(THREADED, resolve(cfg), host=0, seed=0)

    async def go():
        await fleet.reset_group(0)
        results, _ = await fleet.run_chunk(0, [0, 1], np.zeros((2, 4, 1), np.float32))
        return results

    try:
        results = asyncio.run(go())
        assert all(isinstance(r, ChunkResult) and r.steps == 4 for r in results)
        for worker in fleet.live():
            assert worker.home == tuple(CORES[:2])
            assert all(a == set(CORES[:2]) for a in threads_affinity(worker.proc.pid))
        assert fleet.cores() == CORES[:2]
        fleet.pin(CORES[1:2])  # a smaller budget (the allocator's re-plan): every thread moves
        for worker in fleet.live():
            assert all(a == {CORES[1]} for a in threads_affinity(worker.proc.pid))
    finally:
        fleet.close()


# --- the stepping choice ----------------------------------------------------------------------------------------


def feed(choice: SteppingChoice, now: float, rate: dict[int, float], until: float, used: float):
    """Chunks of 8 1-ms steps every 0.05 s at the given env steps/s per mode, each env keeping ``used`` cores busy,
    until a decision or ``until``."""
    decided = None
    while now < until and decided is None:
        now += 0.05
        choice.observe(now, int(rate[choice.mode] * 0.05), [0.001] * 8, 0.05, used)
        decided = choice.tick(now)
    return now, decided


def test_a_multi_threaded_env_is_never_rebound():
    faster = {PINNED: 1000, REBIND: 1300}  # a trial alone would keep rebinding
    single = SteppingChoice(now=0.0, warmup_s=0.0, steady_version=0)
    feed(single, 0.0, faster, 60.0, used=0.98)
    assert single.mode == REBIND

    multi = SteppingChoice(now=0.0, warmup_s=0.0, steady_version=0)
    _, decided = feed(multi, 0.0, faster, 60.0, used=2.1)
    assert multi.mode == PINNED and "keeps 2.1 cores busy" in decided and "sim.cores_per_env = 2" in decided

    # rebinding was chosen, then the simulator starts stepping on several threads: pinned at the next check
    now, decided = feed(single, 60.0, faster, 120.0, used=3.0)
    assert single.mode == PINNED and decided.startswith("pinned: ") and "sim.cores_per_env = 3" in decided
    feed(single, now, faster, now + 600.0, used=3.0)  # no trial comes back while it stays multi-threaded
    assert single.mode == PINNED and not single.trial


# --- the allocator ------------------------------------------------------------------------------------------------


def pool_of(n: int) -> ResourcePool:
    return ResourcePool(cores=[Core(i, 0) for i in range(n)], num_gpus=0)


def threaded_profiles(n: int, per_env: int) -> Profiles:
    """A simulator whose env keeps ``per_env`` cores busy: confined to fewer, its threads take turns and
    it slows down by more than the cores it lost (0.8x on top)."""
    sim = {(c, e, c * e): 100.0 * e * (1.0 if c >= per_env else 0.8 * c / per_env)
           for c in range(1, per_env + 1) for e in range(1, n // c + 1)}
    return Profiles(sim=sim, gen={(c, 8): 400.0 * min(c, 2) for c in range(1, n + 1)},
                    train={(c, 64): 300.0 * min(c, 2) for c in range(1, n + 1)}, sim_cores_used=float(per_env))


def test_profile_candidates_follow_the_cores_an_env_uses():
    assert profile_mod.cores_per_env_candidates(1.0, 8) == [1]
    assert profile_mod.cores_per_env_candidates(float("nan"), 8) == [1]
    assert profile_mod.cores_per_env_candidates(1.3, 8) == [1, 2]
    assert profile_mod.cores_per_env_candidates(1.6, 8) == [1, 2]
    assert profile_mod.cores_per_env_candidates(1.6, 1) == [1]
    assert profile_mod.cores_per_env_candidates(2.9, 8) == [1, 2, 3]
    assert profile_mod.cores_per_env_candidates(5.0, 2) == [1, 2]


def test_the_allocator_gives_each_env_the_cores_it_uses_and_keeps_that_on_re_plans():
    placement = EmbodiPlacement(pool_of(8), threaded_profiles(8, per_env=2), window=3, gap=0.15, patience=3)
    first = placement.apply().applied
    assert first.allocation.c_env == 2 and first.allocation.s_sim == 2 * first.allocation.E
    a = first.allocation
    for _ in range(12):  # training far slower than predicted: re-plans move cores, not cores per env
        placement.balance(StageRates(sim=a.T_sim, gen=a.T_gen, train=a.T_train / 4)).apply()
    assert placement.applied.version > first.version
    assert all(plan.allocation.c_env == 2 for plan in placement.history)
    single = EmbodiPlacement(pool_of(8), threaded_profiles(8, per_env=1)).plan
    assert single.allocation.c_env == 1
    shared = EmbodiPlacement(pool_of(2), threaded_profiles(2, per_env=2)).plan  # sharing every core
    assert shared.allocation.c_env == 2 and shared.allocation.E == 1


def test_a_profile_probes_the_cores_an_env_uses_before_its_simulator_table(tmp_path):
    cfg = config.from_dict({"env": {"id": "Pendulum-v1"}, "run": {"output_dir": str(tmp_path)}})
    pool = ResourcePool(cores=[Core(c, 0) for c in CORES[:2]], num_gpus=0)
    grid = {"sim_envs": [1, len(pool.cores)], "cores": [1], "gen_batch": [4], "train_batch": [cfg.train.batch_size]}
    profiles = profile_mod.profile(pool, cfg, seconds=0.2, grid=grid, progress=False)
    assert profiles.sim_cores_used is not None and 0 < profiles.sim_cores_used <= 1.05
    assert {key[0] for key in profiles.sim} == {1}  # single-threaded: one core per env, as before
    path = tmp_path / "p.json"
    profile_mod.save(path, profiles, {"t": 1})
    assert profile_mod.load(path, {"t": 1}, 60).sim_cores_used == profiles.sim_cores_used


def test_the_initial_plan_writes_cores_per_env_into_the_config(tmp_path):
    cfg = config.from_dict({"alloc": {"enabled": True, "profile_path": str(tmp_path / "p.json")},
                            "run": {"output_dir": str(tmp_path)}})
    from ebrl.alloc.runtime import initial_config

    pool = ResourcePool(gpu_pool=cfg.alloc.gpu_pool, cpu_pool=cfg.alloc.cpu_pool)
    n = len(pool.cores)
    profiles = threaded_profiles(n, per_env=min(2, n))
    profile_mod.save(tmp_path / "p.json", profiles, profile_mod.fingerprint(pool, cfg))
    new, _, line = initial_config(cfg)
    assert new.sim.cores_per_env == min(2, n) and "reused profile" in line
    rebinding = dataclasses.replace(cfg, sim=dataclasses.replace(cfg.sim, core_rebinding=True))
    assert initial_config(rebinding)[0].sim.cores_per_env == 1  # rebinding single steps, as asked: one core each


# --- end to end -----------------------------------------------------------------------------------------------------


@two_cores
def test_a_multi_threaded_user_env_runs_on_its_own_cores_end_to_end(tmp_path, monkeypatch):
    from helpers import run_collecting_stats

    monkeypatch.setenv("PYTHONPATH", str(Path(__file__).resolve().parent))  # the user's env package
    code, out, stats = run_collecting_stats(
        tmp_path / "runs", "configs/quickstart.toml", "run.iterations=2", f'env.id="{THREADED.id}"',
        "sim.cores_per_env=2", "sim.groups=2", "sim.envs_per_group=2", "train.batch_size=64",
        run="threaded")
    assert code == 0, out
    used = [m["sim/env_cores_used"] for m in stats["sim/0"] if "sim/env_cores_used" in m]
    assert used and all(u > 0 for u in used)
    assert "sim/core_rebinding" not in stats["sim/0"][-1]  # pinned sets: no stepping trial
