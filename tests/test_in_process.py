"""Every kind of service in one process on the in-memory bus (``ebrl.testing.InProcessRun``): eval, log and viz
beside sim, gen and train, the allocator re-planning a run, an off-policy run's replay; each uses only the keys
its role declares in ebrl/graph.py (the recording bus of tests/test_graph.py), every service of the graph among
them."""

from __future__ import annotations

import asyncio
import csv

from ebrl import autotune, config
from ebrl import keys
from ebrl.testing import InProcessRun
from helpers import store_profile
from test_graph import recording, undeclared
from test_metrics import assert_catalogued
from test_pipeline import ROOT, small_config


def test_eval_log_and_viz_evaluate_versions_and_write_every_metric_in_process(tmp_path):
    cfg = small_config(tmp_path, eval={"every": 1, "episodes": 2, "video_episodes": 0},
                       log={"tensorboard": True, "csv": True, "flush_s": 0.2}, viz={"rerun": "save"})
    used: dict[str, set[tuple[str, str]]] = {}

    async def main():
        async with InProcessRun(cfg, ("train", "gen", "sim", "eval", "log", "viz"), tmp_path,
                                recording(used)) as run:
            stats = run.stats
            await stats.until(lambda: stats.latest("eval/0", "eval/version", 0) >= 1, 180, "an evaluation of v1")
            await stats.until(lambda: stats.latest("log/0", "log/points", 0) > 0, 60, "log writing points")
            await stats.until(lambda: stats.latest("viz/0", "viz/reports", 0) > 0, 60, "viz logging reports")
        return run

    run = asyncio.run(main())
    report = run.stats.latest_report("eval/0", "eval/return")
    assert report.metrics["eval/episodes"] == 2 and report.metrics["eval/version"] >= 1
    assert (tmp_path / "best.safetensors").is_file()  # the best evaluated version, kept by eval
    with open(tmp_path / "metrics.csv", newline="") as fh:
        written = {row["key"] for row in csv.DictReader(fh)}
    assert {"train/policy_version", "gen/policy_version", "sim/env_steps", "eval/return"} <= written
    assert any((tmp_path / "tb").rglob("events.out.tfevents.*"))
    assert not undeclared(used), undeclared(used)
    assert_catalogued(run.stats.reports())  # every metric of every service is on docs/stats.md
    # and the run did use the data flows the graph draws
    assert ("put", keys.obs("pipe", 0)) in used["sim"] and ("put", keys.weights("pipe")) in used["train"]
    assert ("sub", keys.obs("pipe")) in used["gen"] and ("answer", keys.weights_all("pipe")) in used["train"]
    assert ("sub", keys.stats_all("pipe")) in used["viz"] and ("token", keys.live("pipe", "viz", 0)) in used["viz"]
    assert (tmp_path / "timeline.rrd").is_file()  # what viz logged to rerun


def test_the_allocator_observes_the_stages_re_plans_and_the_services_apply_it_in_process(tmp_path):
    """The allocator's plumbing, in seconds (tests/test_alloc_service.py runs the real processes and checks the
    plan it makes): it starts from the stored profile's plan, turns the stages' stats into capacities, re-plans
    on an imbalance (alloc.gap tiny and alloc.patience 1: any will do) and pushes cores and quotas that sim, gen
    and train apply. In one process every stage reports the same process CPU, so the capacities say nothing
    about the stages here."""
    cfg = small_config(tmp_path, alloc={"enabled": True, "window": 2, "patience": 1, "gap": 1e-3})
    roles = ("train", "gen", "sim", "alloc")
    cfg, _ = autotune.settle(cfg, roles, multi=False)
    store_profile(tmp_path / "profiles" / "pipe.json", cfg, gen_batches=(2, 4), train_batch=64)
    used: dict[str, set[tuple[str, str]]] = {}

    async def main():
        async with InProcessRun(cfg, roles, tmp_path, recording(used)) as run:
            stats = run.stats
            await stats.until(lambda: stats.latest("alloc/0", "alloc/reallocations", 0) >= 1, 180, "a re-allocation")
            await stats.until(lambda: all(stats.latest(f"{s}/0", "ctl/affinity_applied", 0) for s in roles[:3]),
                              60, "sim, gen and train applying the re-allocated cores")
        return run

    run = asyncio.run(main())
    # capacities are in the reports of the windows whose stats could tell them (on a loaded machine not every one)
    assert run.stats.latest("alloc/0", "alloc/plan_version") >= 2
    assert run.stats.latest("alloc/0", "alloc/train_capacity", 0.0) > 0
    assert not undeclared(used), undeclared(used)
    assert_catalogued(run.stats.reports())  # the allocator's and ctl/*_applied among them


def test_an_off_policy_run_asks_its_replay_service_for_minibatches_in_process(tmp_path):
    """SAC with its replay service beside sim, gen and train: training sends each update's transitions and asks
    for minibatches (ReplayRequest), the replay answers (ReplaySample); both use only the keys the graph declares."""
    raw = config.read(ROOT / "configs" / "sac_pendulum.toml")
    cfg = small_config(tmp_path, **{name: raw[name] for name in ("env", "policy", "algo")},
                       replay={"batch_size": 32, "learning_starts": 64}, train={"batch_size": 64, "lr": 1e-3})
    used: dict[str, set[tuple[str, str]]] = {}

    async def main():
        async with InProcessRun(cfg, ("replay", "train", "gen", "sim"), tmp_path, recording(used)) as run:
            stats = run.stats
            await stats.until(lambda: stats.latest("train/0", "train/gradient_steps_total", 0) >= 128, 180,
                              "128 gradient steps on the replay's minibatches")
        return run

    run = asyncio.run(main())
    assert run.stats.latest("replay/0", "replay/sampled") >= 128 * 32
    assert not undeclared(used), undeclared(used)
    assert_catalogued(run.stats.reports())  # bus/local among them
    assert ("put", keys.replay("pipe", "request")) in used["train"] and ("sub", keys.replay("pipe", "sample")) in \
        used["train"]
    assert ("put", keys.replay("pipe", "sample")) in used["replay"]


def test_the_tests_above_record_every_service_of_the_graph():
    """Each service of ebrl/graph.py runs on the recording bus in one of the tests above (a service added to the
    graph is added to one of them)."""
    import ast
    from pathlib import Path

    from ebrl import graph

    tree = ast.parse(Path(__file__).read_text())
    started = {c.value for call in ast.walk(tree) if isinstance(call, ast.Call)  # InProcessRun(cfg, ROLES, ...)
               and getattr(call.func, "id", "") == "InProcessRun" and len(call.args) > 1
               for c in ast.walk(call.args[1]) if isinstance(c, ast.Constant)}
    named = {c.value for assign in ast.walk(tree) if isinstance(assign, ast.Assign)  # roles = (...) passed so
             and any(getattr(t, "id", "") == "roles" for t in assign.targets)
             for c in ast.walk(assign.value) if isinstance(c, ast.Constant)}
    assert set(graph.SERVICES) <= started | named, f"never recorded: {set(graph.SERVICES) - started - named}"
