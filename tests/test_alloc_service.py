"""The allocator in a real run: `ebrl up` with alloc.enabled starts every service inside Algorithm 1's plan, the
alloc service measures stage capacities from stats, re-plans and pushes cores/threads/batch, and the services
apply them. The stage profile is written by the test and training is slowed (run.slowdown), so the first plan
and the measured correction are known in advance."""

from __future__ import annotations

import json
import time

from ebrl import config
from ebrl.alloc.algorithm import Profiles
from ebrl.alloc.profile import fingerprint, save
from ebrl.alloc.runtime import capacities
from ebrl.resources.pool import ResourcePool

import helpers


def test_capacities_are_decisions_per_cpu_second_times_cores():
    sim = {"sim/env_steps_per_s": 4000.0, "sim/step_busy_s_per_s": 0.5}
    gen = {"gen/envs_served_per_s": 1000.0, "proc/cpu_percent": 25.0}
    train = {"train/updates_per_s": 0.5, "proc/cpu_percent": 50.0}
    rates = capacities(sim, gen, train, chunk=4, cores={"sim": 1, "gen": 2, "train": 2}, batch_size=1024)
    assert (rates.sim, rates.gen, rates.train, rates.achieved) == (2000.0, 8000.0, 2048.0, 1000.0)
    assert rates.rollout == 2000.0
    idle = dict(gen, **{"proc/cpu_percent": 1.0})
    assert capacities(sim, idle, train, chunk=4, cores={"sim": 1, "gen": 2, "train": 2}, batch_size=1024) is None


def test_up_with_the_allocator_re_plans_from_measurements_and_services_apply_it(tmp_path):
    out_dir = tmp_path / "runs"
    overrides = ["alloc.enabled=true", "alloc.window=4", "alloc.patience=3", "run.iterations=0", "run.name=alloc",
                 'run.slowdown="train=6@0"']
    cfg = config.load(str(helpers.ROOT / "configs/quickstart.toml"),
                      overrides + [f"run.output_dir={json.dumps(str(out_dir))}"])
    pool = ResourcePool(gpu_pool="none")
    n = len(pool.cores)
    # A profile taken before training got slow (run.slowdown: every update takes 6x as long): the simulator
    # scales with cores, the small models do not, and training looks cheap, so sharing every core is predicted
    # best. Measured capacities show training expensive, which favours giving the simulator a core of its own.
    profiles = Profiles(sim={(1, e, e): 1000.0 * 1.6 ** (e - 1) for e in range(1, n + 1)},
                        gen={(c, b): 50_000.0 for c in range(1, n + 1) for b in (4, 8)},
                        train={(c, 1024): 50_000.0 for c in range(1, n + 1)})
    save(out_dir / "profiles" / "alloc.json", profiles, fingerprint(pool, cfg))
    proc, port = helpers.ebrl_up(out_dir, "configs/quickstart.toml", *overrides)
    try:
        deadline = time.monotonic() + 150
        realloc = None
        while time.monotonic() < deadline and realloc is None:
            time.sleep(1.0)
            runs = [p for p in out_dir.iterdir() if p.name.startswith("alloc-")]
            log = runs[0] / "logs" / "alloc-0.log" if runs else None
            if log and log.exists() and "re-allocated" in log.read_text():
                realloc = log.read_text()
        time.sleep(3.0)  # the services apply it and report
    finally:
        proc.send_signal(2)
        out, _ = proc.communicate(timeout=60)
    assert "allocator: reused profile" in out and "plan v1 (all_shared)" in out, out
    assert realloc is not None, f"no re-allocation within 150 s:\n{out}"
    from ebrl.viz import record

    rec = record.read(runs[0])
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
