"""Stage profiling: each stage alone over a grid, into the lookup tables P_sim, P_gen, P_train.

Every rate is in one unit, **decisions per second** (a decision is one action
chunk of one environment, i.e. K env steps), so that the allocator can compare
stages directly:

* simulation: E environments (real env worker processes, each pinned to its own
  core(s), ``c_env`` cores per env) running action chunks concurrently; rate =
  chunks completed per second. On CPU-only hosts the simulator's quota is its
  core count ``E * c_env``. Which ``c_env`` are worth profiling comes from one
  env stepping alone on every core first: the cores it keeps busy while it steps
  (:func:`ebrl.envs.worker.cores_used`, the measure the sim service reports as
  ``sim/env_cores_used`` and its stepping choice watches). A single-threaded
  simulator is profiled at c_env = 1 only; one that keeps u > 1.25 cores busy
  at 1 .. round(u) as well, and Algorithm 1's line 1 picks among them.
* generation: the policy's batched forward pass (``act``) on ``s`` cores with
  ``s`` torch threads at batch ``B``; rate = ``B`` / seconds per forward.
* training: one PPO update (``algo.epochs`` x ``algo.minibatches``) on a batch of
  ``B`` decisions on ``s`` cores; rate = ``B`` / seconds per update — new data
  absorbed per second, so sample reuse (epochs) is accounted for.

Tables are stored as JSON tagged with a fingerprint of the machine and the
workload (:func:`fingerprint`); :func:`load_or_profile` reuses a stored table
until the fingerprint changes or it is older than ``max_age_s``.
"""

from __future__ import annotations

import asyncio
import contextlib
import dataclasses
import hashlib
import json
import math
import os
import platform
import sys
import time
from pathlib import Path
from typing import Any, Callable, Iterator

import numpy as np

from ebrl import config as config_mod, durable
from ebrl.alloc.algorithm import Profiles
from ebrl.resources.pool import ResourcePool

PROFILE_VERSION = 2  # 2: the simulator's cores per env, probed (tables of 1 are re-measured)


def fingerprint(pool: ResourcePool, cfg: config_mod.Config) -> dict[str, Any]:
    """What a profile depends on: the machine and the workload (not the run's name or length)."""
    import torch

    cpu_model = ""
    with contextlib.suppress(OSError):
        cpu_model = next((line.split(":", 1)[1].strip() for line in open("/proc/cpuinfo")
                          if line.startswith("model name")), "")
    workload = {"env": dataclasses.asdict(cfg.env), "policy": dataclasses.asdict(cfg.policy),
                "algo": {k: getattr(cfg.algo, k) for k in ("epochs", "minibatches")},
                "envs_per_group": cfg.sim.envs_per_group, "groups": cfg.sim.groups, "batch_size": cfg.train.batch_size}
    return {"version": PROFILE_VERSION, "host": platform.node(), "cpu": cpu_model, "cores": pool.core_ids,
            "gpus": [g.uuid for g in pool.gpus], "torch": torch.__version__, "python": sys.version.split()[0],
            "workload": hashlib.sha1(json.dumps(workload, sort_keys=True, default=str).encode()).hexdigest()[:16]}


def default_path(cfg: config_mod.Config) -> Path:
    return Path(cfg.alloc.profile_path) if cfg.alloc.profile_path else Path(cfg.run.output_dir) / "profiles" / \
        f"{cfg.run.name}.json"


# --- grids -----------------------------------------------------------------------------------


def grids(pool: ResourcePool, cfg: config_mod.Config) -> dict[str, list]:
    """Default grids: every concurrency 1..cores for simulation, every core count for gen and train,
    batches of whole groups for generation and the configured batch for training."""
    n = len(pool.cores)
    per, groups = cfg.sim.envs_per_group, cfg.sim.groups
    return {"sim_envs": list(range(1, min(n, cfg.num_envs) + 1)),
            "cores": list(range(1, n + 1)),
            "gen_batch": sorted({per * k for k in range(1, groups + 1)}),
            "train_batch": [cfg.train.batch_size]}


# --- measurements ------------------------------------------------------------------------------


@contextlib.contextmanager
def pinned(cores: list[int], threads: int) -> Iterator[None]:
    """Run this process on ``cores`` with ``threads`` torch threads; restore both afterwards."""
    import torch

    before, before_threads = os.sched_getaffinity(0), torch.get_num_threads()
    os.sched_setaffinity(0, cores)
    torch.set_num_threads(threads)
    try:
        yield
    finally:
        os.sched_setaffinity(0, before)
        torch.set_num_threads(before_threads)


def timed(fn: Callable[[], Any], seconds: float, min_reps: int = 3) -> float:
    """Seconds per call of ``fn`` (after one warm-up call), repeated for about ``seconds``."""
    fn()
    reps, start = 0, time.perf_counter()
    while reps < min_reps or time.perf_counter() - start < seconds:
        fn()
        reps += 1
    return (time.perf_counter() - start) / reps


def _run_sim(cfg: config_mod.Config, homes: list[int | tuple[int, ...]], seconds: float) -> tuple[float, list]:
    """One env worker pinned at each of ``homes``, all running random chunks back to back for ``seconds``:
    (chunks per second, every chunk's result)."""
    from ebrl.envs import EnvSpec, EnvWorker, describe

    spec = EnvSpec.from_config(cfg.env)
    act_space = describe(spec).action_space
    rng = np.random.default_rng(0)

    async def run() -> tuple[float, list]:
        workers = [EnvWorker(spec, seed=i, core=home) for i, home in enumerate(homes)]
        results = []
        try:
            await asyncio.gather(*(w.reset() for w in workers))
            chunk = lambda: rng.uniform(act_space.low, act_space.high,  # noqa: E731
                                        (cfg.policy.chunk, act_space.shape[0])).astype(np.float32)
            await asyncio.gather(*(w.chunk(chunk()) for w in workers))  # warm-up
            start = time.perf_counter()

            async def loop(w) -> None:
                while time.perf_counter() - start < seconds:
                    results.append(await w.chunk(chunk()))

            await asyncio.gather(*(loop(w) for w in workers))
            return len(results) / (time.perf_counter() - start), results
        finally:
            for w in workers:
                w.close(timeout=1.0)

    return asyncio.run(run())


def measure_sim(cfg: config_mod.Config, cores: list[int], envs: int, seconds: float, cores_per_env: int = 1) -> float:
    """Decisions/s of ``envs`` env workers running chunks concurrently, each pinned (every thread) to its own
    ``cores_per_env`` of ``cores`` (round-robin when they are fewer than the envs need)."""
    from ebrl.sched.modes import home_cores

    return _run_sim(cfg, [home_cores(cores, cores_per_env, i) for i in range(envs)], seconds)[0]


def measure_cores_used(cfg: config_mod.Config, cores: list[int], seconds: float) -> float:
    """Cores one env keeps busy while it steps, free to run on all of ``cores`` (nothing else running)."""
    from ebrl.envs.worker import cores_used

    return cores_used(_run_sim(cfg, [tuple(cores)], seconds)[1])


def cores_per_env_candidates(cores_used: float, n: int) -> list[int]:
    """The c_env worth profiling for an env that keeps ``cores_used`` cores busy, on ``n`` cores: 1, and for a
    multi-threaded simulator every count up to the cores it uses (rounded)."""
    from ebrl.sched.stepchoice import MULTI_THREADED

    if not cores_used > MULTI_THREADED:  # nan (no step measured) too
        return [1]
    return list(range(1, min(n, max(2, round(cores_used))) + 1))


def _model(cfg: config_mod.Config):
    from ebrl.envs import EnvSpec, describe
    from ebrl.policies import make_policy

    info = describe(EnvSpec.from_config(cfg.env))
    return make_policy(cfg.policy, info.layout, info.action_dim, info.bounds), info.obs_shape, info.action_dim


def measure_gen(cfg: config_mod.Config, cores: list[int], batch: int, seconds: float) -> float:
    """Decisions/s of the policy's batched forward pass at ``batch`` on ``cores``."""
    import torch

    model, obs_shape, _ = _model(cfg)
    model.eval()
    obs = np.random.default_rng(0).standard_normal((batch, *obs_shape)).astype(np.float32)
    with pinned(cores, len(cores)), torch.no_grad():
        return batch / timed(lambda: model.act(obs), seconds)


def measure_train(cfg: config_mod.Config, cores: list[int], batch: int, seconds: float) -> float:
    """Decisions/s absorbed by PPO updates (epochs x minibatches) of ``batch`` decisions on ``cores``."""
    import torch

    from ebrl.algos.ppo import PPO, Batch

    model, obs_shape, action_dim = _model(cfg)
    ppo = PPO(model, cfg.algo, cfg.train.lr)
    g = torch.Generator().manual_seed(0)
    data = Batch(obs=torch.randn((batch, *obs_shape), generator=g),
                 actions=torch.randn((batch, cfg.policy.chunk, action_dim), generator=g),
                 latents=torch.randn((batch, *model.latent_shape), generator=g),
                 logprobs=torch.randn(batch, generator=g) - 5, advantages=torch.randn(batch, generator=g),
                 returns=torch.randn(batch, generator=g), values=torch.randn(batch, generator=g),
                 versions=np.zeros(batch, dtype=np.int64))
    with pinned(cores, len(cores)):
        return batch / timed(lambda: ppo.update(data), seconds, min_reps=2)


# --- the profile -------------------------------------------------------------------------------


class Progress:
    """The profile's progress on stderr: a tqdm bar on a terminal, with what the last point measured; one plain
    line per point otherwise (a log stays readable)."""

    def __init__(self, total: int, out=sys.stderr):
        from tqdm import tqdm

        self.total, self.done, self.out = total, 0, out
        self.bar = tqdm(total=total, desc="profiling", unit="point", file=out, dynamic_ncols=True,
                        disable=not out.isatty())

    def step(self, what: str) -> None:
        self.done += 1
        if self.bar.disable:
            print(f"profiling {self.done}/{self.total}: {what}", file=self.out, flush=True)
            return
        self.bar.set_postfix_str(what, refresh=False)
        self.bar.update()
        if self.done == self.total:
            self.bar.close()


def profile(pool: ResourcePool, cfg: config_mod.Config, seconds: float = 1.0,
            grid: dict[str, list] | None = None, progress: bool = True) -> Profiles:
    """Measure each stage alone over ``grid`` (default :func:`grids`) on the pool's cores (CPU-only:
    quotas are core counts). The simulator is first probed for the cores one env keeps busy
    (:func:`measure_cores_used`), which sets the cores per env (c_env) its table covers
    (:func:`cores_per_env_candidates`); each (c_env, E) is measured with E * c_env cores."""
    grid = grid or grids(pool, cfg)
    cores = pool.core_ids
    used = measure_cores_used(cfg, cores, seconds)
    per_env = cores_per_env_candidates(used, len(cores))
    jobs = ([("sim", e, c) for c in per_env for e in grid["sim_envs"] if e * c <= len(cores)]
            + [("gen", s, b) for s in grid["cores"] for b in grid["gen_batch"]]
            + [("train", s, b) for s in grid["cores"] for b in grid["train_batch"]])
    bar = Progress(len(jobs) + 1) if progress else None
    if bar:
        bar.step(f"sim: one env keeps {used:.2f} cores busy while it steps; cores per env profiled: "
                 f"{', '.join(map(str, per_env))}")
    sim: dict[tuple[int, int, int], float] = {}
    gen: dict[tuple[int, int], float] = {}
    train: dict[tuple[int, int], float] = {}
    for stage, a, b in jobs:
        if stage == "sim":
            sim[(b, a, a * b)] = rate = measure_sim(cfg, cores[:a * b], a, seconds, cores_per_env=b)
            what = f"sim: {a} envs on {b} core{'s' if b > 1 else ''} each: {rate:,.0f} decisions/s"
        elif stage == "gen":
            gen[(a, b)] = rate = measure_gen(cfg, cores[:a], b, seconds)
            what = f"gen: {a} cores, batch {b}: {rate:,.0f} decisions/s"
        else:
            train[(a, b)] = rate = measure_train(cfg, cores[:a], b, seconds)
            what = f"train: {a} cores, batch {b}: {rate:,.0f} decisions/s"
        if bar:
            bar.step(what)
    return Profiles(sim=sim, gen=gen, train=train, sim_cores_used=used if math.isfinite(used) else None)


def save(path: Path, profiles: Profiles, tag: dict[str, Any]) -> None:
    path.parent.mkdir(parents=True, exist_ok=True)
    # a reader sees the old file or the new one (ebrl.durable)
    durable.write_text(path, json.dumps({"fingerprint": tag, "created": time.time(), "profiles": profiles.to_json()},
                                        indent=1))


def load(path: Path, tag: dict[str, Any], max_age_s: float) -> Profiles | None:
    """The stored tables if they match ``tag`` and are fresh enough, else None."""
    try:
        stored = json.loads(path.read_text())
    except (OSError, ValueError):
        return None
    if stored.get("fingerprint") != tag or time.time() - stored.get("created", 0) > max_age_s:
        return None
    return Profiles.from_json(stored["profiles"])


def load_or_profile(pool: ResourcePool, cfg: config_mod.Config, path: Path | None = None, force: bool = False,
                    seconds: float = 1.0, progress: bool = True) -> tuple[Profiles, Path, bool]:
    """(tables, file, measured_now): reuse a fresh stored profile of this machine and workload, else measure."""
    path = path or default_path(cfg)
    tag = fingerprint(pool, cfg)
    if not force:
        stored = load(path, tag, cfg.alloc.profile_max_age_h * 3600)
        if stored is not None:
            return stored, path, False
    profiles = profile(pool, cfg, seconds=seconds, progress=progress)
    save(path, profiles, tag)
    return profiles, path, True
