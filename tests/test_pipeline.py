"""The middle layer: sim, gen and train services together in ONE process over the in-memory bus
(``ebrl.testing.InProcessRun``).

Real env workers (InvertedPendulum), real torch models, the real group loop, learner and weights protocol;
only the transport is in memory, so a few iterations take seconds and every message is inspectable.
"""

from __future__ import annotations

import asyncio
import math
from pathlib import Path

import numpy as np
import pytest

from ebrl import config
from ebrl import keys
from ebrl.messages import ActionChunk, SegmentBatch, StatsReport, TrajectorySegment
from ebrl.sched.modes import resolve
from ebrl.testing import InProcessRun

ROOT = Path(__file__).resolve().parent.parent


def small_config(tmp_path: Path, **sections: dict) -> config.Config:
    raw = config.read(ROOT / "configs" / "quickstart.toml")
    small = {"run": {"name": "pipe", "iterations": 0, "stats_interval": 0.2, "output_dir": str(tmp_path)},
             "sim": {"groups": 2, "envs_per_group": 2, "segment_length": 8},
             "train": {"batch_size": 64}, "algo": {"epochs": 1, "minibatches": 2}, "viz": {"rerun": "off"}}
    for name, values in [*small.items(), *sections.items()]:
        raw.setdefault(name, {}).update(values)
    return config.from_dict(raw)


async def run_services(cfg: config.Config, tmp_path: Path, until, timeout: float = 120.0):
    """Start train, gen and sim in this process; ``until(watch)`` is awaited (``watch``: a bus that sees what
    they publish); then every service is stopped and must exit 0. The services, in that order."""
    async with InProcessRun(cfg, ("train", "gen", "sim"), tmp_path) as run:
        await asyncio.wait_for(until(run.watch), timeout)
    return run.services


def segments_until_version(seen: dict, version: int = 3):
    """A run's ``until``: collect every segment (``seen["segments"]``) and gen's reported policy versions
    (``seen["versions"]``) until gen acts with ``version``."""
    async def until(watch):
        segments = watch.subscribe(keys.traj("pipe"), TrajectorySegment, capacity=1024)
        packed = watch.subscribe(keys.traj_packed("pipe"), SegmentBatch, capacity=1024)  # vectorized groups'
        stats = watch.subscribe(keys.stats("pipe", "*", 0), StatsReport, capacity=256)
        while True:
            seen["segments"] += [seg for _, seg in segments.drain()]
            seen["segments"] += [seg for _, batch in packed.drain() for seg in batch.segments()]
            for _, report in stats.drain():
                if report.service == "gen":
                    seen["versions"].append(report.metrics["gen/policy_version"])
            if seen["versions"] and max(seen["versions"]) >= version:
                return
            await asyncio.sleep(0.05)

    return until


def test_sim_gen_and_train_learn_together_in_one_process(tmp_path):
    cfg = small_config(tmp_path)
    seen: dict[str, list] = {"segments": [], "versions": []}
    sim, gen, train = reversed(asyncio.run(_run(cfg, tmp_path, segments_until_version(seen))))
    segments = seen["segments"]
    assert train.learner.version >= 3 and gen.version >= 3  # versions advanced, and gen acted with them
    assert {s.group for s in segments} == {0, 1} and {s.env_id for s in segments} == {0, 1, 2, 3}
    assert max(int(s.versions.max()) for s in segments) >= 1  # segments acted by weights trained here
    assert all(int(s.versions.max()) <= train.learner.version for s in segments)
    assert train.meter.total("train/segments_received") >= 8
    assert sim.meter.total("sim/segments") >= len(segments) > 0
    assert sum(sim.bus.malformed.values()) == sum(train.bus.malformed.values()) == 0
    assert (tmp_path / "policy.safetensors").is_file()  # the trained policy, saved at the stop


async def _run(cfg, tmp_path, until):
    return await run_services(cfg, tmp_path, until)


async def watch_chunks_and_updates(watch, seen: dict, versions: int) -> None:
    """Collect every action chunk gen sends and every train report, until train made ``versions``."""
    chunks = watch.subscribe(keys.act("pipe"), ActionChunk, capacity=4096)
    stats = watch.subscribe(keys.stats("pipe", "train", 0), StatsReport, capacity=256)
    while True:
        seen["chunks"] += [chunk for _, chunk in chunks.drain()]
        for _, report in stats.drain():
            seen["reports"].append(report.metrics)
            if report.metrics["train/policy_version"] >= versions:
                return
        await asyncio.sleep(0.05)


@pytest.mark.parametrize("mode, max_staleness", [("ebrl", 1), ("colocated", 0), ("hybrid", 0), ("async", 2)])
def test_every_mode_keeps_its_staleness_bound(tmp_path, mode, max_staleness):
    """Generation answers chunk ``seq`` of iteration i only with version >= i - max_staleness (0 without
    overlap), and training learns only from decisions at most that many versions old (async with the
    interpolated proximal log-probs, the others recomputing them)."""
    prox = "interpolate" if mode == "async" else "recompute"
    cfg = small_config(tmp_path, run={"mode": mode}, algo={"max_staleness": max_staleness, "prox_logp": prox})
    seen: dict = {"chunks": [], "reports": []}
    asyncio.run(_run(cfg, tmp_path, lambda watch: watch_chunks_and_updates(watch, seen, 4)))
    schedule = resolve(cfg)
    assert schedule.max_staleness == max_staleness
    assert len(seen["chunks"]) > 0
    for chunk in seen["chunks"]:
        assert chunk.policy_version >= schedule.min_version(chunk.seq), (chunk.seq, chunk.policy_version)
    lags = [m["train/staleness_max"] for m in seen["reports"] if "train/staleness_max" in m]
    assert lags and max(lags) <= max_staleness


@pytest.mark.gpu
@pytest.mark.skipif(not __import__("torch").cuda.is_available(),
                    reason="needs a CUDA device (benchmarks/gpu/check.sh runs it on a GPU machine)")
@pytest.mark.parametrize("kind,compile", [("mlp", "off"), ("flow", "off"), ("flow", "cudagraphs")])
def test_generation_and_training_share_the_gpu(tmp_path, kind, compile):
    """gen and train on CUDA (``auto`` picks it), the policy learning, and every report saying so; with
    ``gen.compile = "cudagraphs"`` generation replays captured graphs."""
    cfg = small_config(tmp_path, policy={"kind": kind, "denoise_steps": 3}, gen={"compile": compile})
    seen: dict = {"chunks": [], "reports": []}
    gen_reports: list[dict] = []

    async def until(watch):
        stats = watch.subscribe(keys.stats("pipe", "gen", 0), StatsReport, capacity=256)
        await watch_chunks_and_updates(watch, seen, 4)
        gen_reports.extend(r.metrics for _, r in stats.drain())

    services = asyncio.run(_run(cfg, tmp_path, until))
    train, gen = services[0], services[1]
    assert train.learner.device.type == "cuda" and gen.device.type == "cuda"
    assert seen["reports"][-1]["train/cuda_device"] == 0 and gen_reports[-1]["gen/cuda_device"] == 0
    assert seen["reports"][-1]["train/cuda_mem_allocated_mb"] > 0
    assert (tmp_path / "policy.safetensors").is_file()
    assert bool(gen.actor.graphs) == (compile == "cudagraphs")


def test_bfloat16_autocast_runs_generation_and_training(tmp_path):
    """``policy.dtype = "bfloat16"`` (measured on a GPU before it could become a default; CPUs run it too)."""
    cfg = small_config(tmp_path, policy={"kind": "flow", "denoise_steps": 3, "dtype": "bfloat16"})
    seen: dict = {"chunks": [], "reports": []}
    asyncio.run(_run(cfg, tmp_path, lambda watch: watch_chunks_and_updates(watch, seen, 2)))
    losses = [m["train/policy_loss"] for m in seen["reports"] if "train/policy_loss" in m]
    assert losses and all(math.isfinite(x) for x in losses)
    assert all(c.actions.dtype.name == "float32" and np.isfinite(c.logprobs).all() for c in seen["chunks"])
