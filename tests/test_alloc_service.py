"""The allocator in a real run: `ebrl up` with alloc.enabled starts every service inside Algorithm 1's plan, the
alloc service measures stage capacities from stats, re-plans and pushes cores/threads/batch, and the services
apply them. The stage profile is written by the test and training is slowed (run.slowdown), so the first plan
and the measured correction are known in advance."""

from __future__ import annotations

import pytest

import json
import time

from ebrl import autotune, config
from ebrl.alloc.runtime import capacities
from ebrl.resources.pool import ResourcePool
from ebrl.testing import StatsWatcher

import helpers
from test_metrics import assert_catalogued


def test_capacities_are_decisions_per_cpu_second_times_cores():
    sim = {"sim/env_steps_per_s": 4000.0, "sim/step_busy_s_per_s": 0.5}
    gen = {"gen/envs_served_per_s": 1000.0, "proc/cpu_percent": 25.0}
    train = {"train/updates_per_s": 0.5, "proc/cpu_percent": 50.0}
    rates = capacities(sim, gen, train, chunk=4, cores={"sim": 1, "gen": 2, "train": 2}, batch_size=1024)
    assert (rates.sim, rates.gen, rates.train, rates.achieved) == (2000.0, 8000.0, 2048.0, 1000.0)
    assert rates.rollout == 2000.0
    idle = dict(gen, **{"proc/cpu_percent": 1.0})
    assert capacities(sim, idle, train, chunk=4, cores={"sim": 1, "gen": 2, "train": 2}, batch_size=1024) is None


# slow: its plumbing runs in seconds in tests/test_in_process.py; this real run checks the plan it makes
@pytest.mark.slow
def test_up_with_the_allocator_re_plans_from_measurements_and_services_apply_it(tmp_path):
    out_dir = tmp_path / "runs"
    overrides = ["alloc.enabled=true", "alloc.window=4", "alloc.patience=3", "run.iterations=0", "run.name=alloc",
                 'run.slowdown="train=6@0"']
    cfg = config.load(str(helpers.ROOT / "configs/quickstart.toml"),
                      overrides + [f"run.output_dir={json.dumps(str(out_dir))}"])
    cfg, _ = autotune.settle(cfg, ("sim", "gen", "train", "alloc"), multi=False)  # as the launcher profiles it
    # A profile taken before training got slow (run.slowdown: every update takes 6x as long) predicts sharing
    # every core best. Measured capacities show training expensive, which favours giving the simulator a core
    # of its own.
    helpers.store_profile(out_dir / "profiles" / "alloc.json", cfg, gen_batches=(4, 8), train_batch=1024)
    n = len(ResourcePool(gpu_pool="none").cores)
    with helpers.up(out_dir, "configs/quickstart.toml", *overrides, name="alloc") as run, \
            StatsWatcher(run) as stats:
        stats.wait_for(lambda: (stats.latest("alloc/0", "alloc/reallocations") or 0) >= 1, 600, "a re-allocation")
        stats.wait_for(lambda: all(stats.latest(f"{s}/0", "ctl/affinity_applied") for s in ("sim", "gen", "train")),
                       300, "sim, gen and train applying the re-allocated cores")
        run.stop()
    out = run.output
    assert "allocator: reused profile" in out and "plan v1 (all_shared)" in out, out
    assert "re-allocated" in (run.run_dir / "logs" / "alloc-0.log").read_text()
    from ebrl.viz import record

    rec = record.read(run.run_dir)
    kinds = [(e.service, e.kind) for e in rec.events]
    assert ("alloc", "realloc") in kinds
    for stage in ("sim", "gen", "train"):
        assert (stage, "affinity") in kinds, kinds  # each service applied the pushed cores
    applied = [r.metrics for r in rec.stats if r.service == "sim" and r.metrics.get("ctl/affinity_applied")]
    # the simulator stopped sharing every core (a later trial may have reverted it: any report counts)
    assert any(m["quota/cores"] < n for m in applied), [m["quota/cores"] for m in applied]
    assert any(s.lane == "alloc" and s.label == "realloc" for s in rec.spans)
    allocs = [r.metrics for r in rec.stats if r.service == "alloc"]
    assert allocs[-1]["alloc/reallocations"] >= 1 and allocs[-1]["alloc/plan_version"] >= 2
    assert_catalogued(rec.stats)  # the allocator's metrics, and ctl/* of the services applying it, on docs/stats.md


def test_a_gpu_plan_starts_generation_and_training_with_their_mps_shares(tmp_path):
    """NVML and the MPS daemon faked at their boundary: a plan's SM shares become each stage's launch env, and a
    re-plan that moves SMs from training to generation replaces the shares whole."""
    import dataclasses

    from ebrl.alloc.placement import EmbodiPlacement
    from ebrl.alloc.runtime import gpu_env, gpu_shares
    from ebrl.alloc.synthetic import random_tables
    from ebrl.resources.pool import Core
    from test_resources import FakeGpuNVML

    (tmp_path / "control").write_text("")  # the MPS control daemon's pipe
    pool = ResourcePool(gpu_pool="mps", nvml=FakeGpuNVML(), cores=[Core(i, 0) for i in range(4)],
                        mps_pipe_dir=str(tmp_path))
    placement = EmbodiPlacement(pool, random_tables(3, monotone=True)).apply()
    a = placement.applied.allocation
    env = gpu_env(placement)
    assert set(env) == {"gen", "train"}  # the simulator's env workers run on the CPU here
    assert env["gen"]["CUDA_MPS_ACTIVE_THREAD_PERCENTAGE"] == f"{a.s_gen:g}"
    assert env["train"]["CUDA_MPS_ACTIVE_THREAD_PERCENTAGE"] == f"{a.s_train:g}"
    memory = pool.gpus[0].memory_bytes
    assert env["gen"]["CUDA_MPS_PINNED_DEVICE_MEM_LIMIT"] == f"0={memory * a.s_gen // 100 // 2**20}M"
    swapped = dataclasses.replace(a, s_gen=a.s_gen + a.s_train - 10, s_train=10)  # generation takes more
    placement.pending = placement._plan(swapped, "test")
    placement.apply()  # one stage at a time, the shares would add up to over 100 %
    assert gpu_env(placement)["gen"]["CUDA_MPS_ACTIVE_THREAD_PERCENTAGE"] == f"{swapped.s_gen:g}"
    # what the allocator tells the launcher of its host: each stage's new share, with the plan's version
    shares = {s.stage: s for s in gpu_shares(placement)}
    assert set(shares) == {"gen", "train"} and {s.version for s in shares.values()} == {placement.applied.version}
    assert shares["train"].env == gpu_env(placement)["train"]
    assert shares["train"].env["CUDA_MPS_ACTIVE_THREAD_PERCENTAGE"] == "10"


LAUNCH_WITH_GPU_SHARES = """
import asyncio, logging, sys
from ebrl import config
from ebrl.bus import auth
from ebrl.launch import Launcher
from ebrl.prepare import make_run_dir
cfg = config.load(sys.argv[1], sys.argv[2:])
run_dir = make_run_dir(cfg)
if auth.secret_path(cfg.bus, run_dir):  # as `ebrl up` does before anything starts (bus.auth, the default)
    auth.ensure(auth.secret_path(cfg.bus, run_dir))
(run_dir / "config.toml").write_text(config.dump_toml(cfg))
share = {"CUDA_VISIBLE_DEVICES": "0", "CUDA_MPS_ACTIVE_THREAD_PERCENTAGE": "50",
         "CUDA_MPS_PINNED_DEVICE_MEM_LIMIT": "0=1024M"}
sys.exit(asyncio.run(Launcher(cfg, run_dir, gpu_env={"gen": share, "train": dict(share)}).main()))
"""


@pytest.mark.slow
def test_a_new_gpu_share_restarts_training_at_a_safe_point_and_loses_nothing(tmp_path):
    """What the launcher does when the allocator tells it of a new SM share (``GpuShare``; the GPU faked at its
    boundary: the share is only the environment a process starts with): train stops after its update, hands
    over its state and the segments not yet trained on, and starts again with the new share; the run goes on."""
    import subprocess
    import sys

    import msgpack
    import psutil
    import zenoh

    from ebrl import keys
    from ebrl.bus.session import BusOptions, zenoh_config
    from ebrl.messages import GpuShare, encode_message
    from ebrl.viz import record

    port = helpers.free_port()
    cmd = [sys.executable, "-c", LAUNCH_WITH_GPU_SHARES, str(helpers.ROOT / "configs/quickstart.toml"),
           "run.iterations=14", "run.name=requota", f"run.output_dir={json.dumps(str(tmp_path))}",
           f'bus.listen=["tcp/127.0.0.1:{port}"]', "run.stats_interval=0.5", 'viz.rerun="off"']
    proc = subprocess.Popen(cmd, cwd=helpers.ROOT, stdout=subprocess.PIPE, stderr=subprocess.STDOUT, text=True)
    deadline = time.monotonic() + 600  # a bound for a hang, not a timing window
    while not list(tmp_path.glob("requota-*/config.toml")):  # written after the run's secret
        assert proc.poll() is None and time.monotonic() < deadline, "the launcher wrote no config.toml"
        time.sleep(0.1)
    secret = [str(path) for path in tmp_path.glob("requota-*/bus.secret")]  # with bus.auth = true
    # as the run's allocator would publish a GPU share. This run starts no allocator, so its launcher admits no
    # alloc instance (ebrl.bus.auth: an identity per instance) and no role line: sign in as a launcher, which may
    conf = zenoh_config(BusOptions(mode="client", connect=[f"tcp/127.0.0.1:{port}"], listen=[],
                                   secret_file=secret[0] if secret else "", role="launcher"))
    versions: list[float] = []

    def on_stats(sample) -> None:
        versions.append(msgpack.unpackb(sample.payload.to_bytes())["metrics"].get("train/policy_version", -1))

    def train_share() -> str | None:
        for child in psutil.Process(proc.pid).children(recursive=True):
            try:
                if "ebrl.services.train" in child.cmdline():
                    return child.environ().get("CUDA_MPS_ACTIVE_THREAD_PERCENTAGE")
            except psutil.Error:
                pass
        return None

    session = None
    try:
        while session is None:  # config.toml is written before the launcher listens: connect once it does
            try:
                session = zenoh.open(conf)
            except zenoh.ZError:
                assert proc.poll() is None, f"the launcher exited:\n{proc.communicate()[0]}"
                assert time.monotonic() < deadline, "the launcher never listened"
                time.sleep(0.2)
        with session:
            session.declare_subscriber(keys.stats("requota", "train", 0), on_stats)
            deadline = time.monotonic() + 600  # a bound for a hang, not a timing window
            while max(versions, default=0) < 4:
                assert proc.poll() is None and time.monotonic() < deadline, "no fourth update in 600 s"
                time.sleep(0.2)
            assert train_share() == "50"  # started with the allocator's first share
            session.put(keys.gpu_share("requota", 0), encode_message(GpuShare(version=2, stage="train", env={
                "CUDA_VISIBLE_DEVICES": "0", "CUDA_MPS_ACTIVE_THREAD_PERCENTAGE": "30",
                "CUDA_MPS_PINNED_DEVICE_MEM_LIMIT": "0=2048M"})))
            while train_share() != "30":
                assert proc.poll() is None and time.monotonic() < deadline, "train never came back with 30 %"
                time.sleep(0.2)
            out, _ = proc.communicate(timeout=600)
    finally:
        proc.kill()
    assert proc.returncode == 0, out
    (run,) = [p for p in tmp_path.iterdir() if p.is_dir()]
    done = json.loads((run / "summary.json").read_text())
    assert done["iterations"] == 14 and done["restarts"] == {}  # a new share is no failure
    log = (run / "logs" / "train-0.log").read_text()
    assert "--- with GPU share" in log and "resumed from" in log  # ... it went on from the stopped train's state
    assert "took over" in log  # ... and with the segments it had not trained on yet
    rec = record.read(run)
    assert any(e.kind == "requota" and "train/0" in e.text for e in rec.events)
    seen = [v for v in versions if v >= 0]
    assert seen == sorted(seen)  # versions never went back
    sims = [r.metrics for r in rec.stats if r.service == "sim"]
    held = max(m.get("sim/segments_while_train_down", 0) for m in sims)
    late = max(m.get("sim/segments_sent_late", 0) for m in sims)
    assert late > 0 or held == 0  # what the simulator held while no train was live went to the new one
