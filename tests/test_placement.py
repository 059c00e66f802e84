"""The allocator's programming API (EmbodiPlacement) and stage profiles on CPU: real pools, synthetic rates."""

from __future__ import annotations

import dataclasses
import json

import pytest

from ebrl import config
from ebrl.alloc import profile as profile_mod
from ebrl.alloc.algorithm import Profiles
from ebrl.alloc.placement import EmbodiPlacement, StageRates
from ebrl.resources.pool import Core, ResourcePool


def cpu_profiles(n: int, sim_per_core=100.0, gen_per_core=150.0, train_per_core=120.0, saturate=4) -> Profiles:
    """A CPU-only host: E envs on E cores scale linearly; generation and training stop scaling at ``saturate``
    cores (small models do), in decisions/s."""
    return Profiles(sim={(1, e, e): sim_per_core * e for e in range(1, n + 1)},
                    gen={(c, b): gen_per_core * min(c, saturate) * (1 if b == 8 else 0.8)
                         for c in range(1, n + 1) for b in (4, 8)},
                    train={(c, 64): train_per_core * min(c, saturate) for c in range(1, n + 1)})


def pool_of(n: int) -> ResourcePool:
    return ResourcePool(cores=[Core(i, 0) for i in range(n)], num_gpus=0)


def test_initial_plan_partitions_cores_and_apply_binds_them():
    applied = []
    placement = EmbodiPlacement(pool_of(8), cpu_profiles(8), on_apply=applied.append)
    plan = placement.plan
    alloc = plan.allocation
    assert alloc.s_sim + alloc.s_gen + alloc.s_train == 8 and alloc.B_gen == 8
    assert sorted(plan.cores["sim"] + plan.cores["gen"] + plan.cores["train"]) == list(range(8))
    assert alloc.theta == pytest.approx(min(100 * alloc.s_sim, 150 * alloc.s_gen, 120 * alloc.s_train))
    placement.apply()
    assert applied == [plan] and placement.pending is None
    assert placement.bindings()["train/0"].cores == plan.cores["train"]
    assert placement.bindings()["gen/0"].threads == len(plan.cores["gen"])
    placement.apply()  # nothing pending: no-op
    assert len(applied) == 1


def test_two_cores_choose_between_sharing_every_core_and_isolating_the_simulator():
    # Stages that scale with cores share the two best; isolating the simulator wins when the models do not scale.
    shared = EmbodiPlacement(pool_of(2), cpu_profiles(2, saturate=2)).plan
    assert shared.allocation.method == "all_shared" and shared.cores == {"sim": [0, 1], "gen": [0, 1], "train": [0, 1]}
    assert shared.allocation.theta == pytest.approx(1 / (1 / 200 + 1 / 300 + 1 / 240))
    isolated = EmbodiPlacement(pool_of(2), cpu_profiles(2, gen_per_core=300, train_per_core=300, saturate=1)).plan
    assert isolated.allocation.method == "shared"  # gen and train time-share core 1
    assert isolated.cores == {"sim": [0], "gen": [1], "train": [1]}


def test_balance_waits_for_a_sustained_gap_then_gives_the_slow_stage_more():
    steady = EmbodiPlacement(pool_of(8), cpu_profiles(8), window=5, gap=0.15, patience=5).apply()
    a = steady.applied.allocation
    for _ in range(30):  # measured as predicted: whatever Algorithm 1 reruns, the plan stays
        steady.balance(StageRates(sim=a.T_sim, gen=a.T_gen, train=a.T_train)).apply()
    assert steady.history == [steady.applied]

    placement = EmbodiPlacement(pool_of(8), cpu_profiles(8), window=5, gap=0.15, patience=5).apply()
    before = placement.applied
    slow = StageRates(sim=a.T_sim, gen=a.T_gen, train=a.T_train / 3)  # training got 3x slower
    for i in range(8):  # 4 to fill the window, then 5 over the gap
        placement.balance(slow)
        assert placement.pending is None, f"re-planned after only {i + 1} observations"
    placement.balance(slow)
    assert placement.pending is not None and "for 5 reports" in placement.pending.reason
    placement.apply()
    after = placement.applied
    assert after.version == before.version + 1 and placement.history == [before, after]
    assert len(after.cores["train"]) > len(before.cores["train"])
    assert placement.balance(StageRates(sim=0.0, gen=1.0, train=1.0)) is placement  # an idle stage tells nothing


def test_a_re_plan_that_achieves_less_is_reverted_and_not_tried_again_soon():
    placement = EmbodiPlacement(pool_of(8), cpu_profiles(8), window=5, gap=0.15, patience=5).apply()
    first = placement.applied
    a = first.allocation
    slow = StageRates(sim=a.T_sim, gen=a.T_gen, train=a.T_train / 3, achieved=100.0)
    while placement.pending is None:
        placement.balance(slow)
    placement.apply()
    tried = placement.applied
    assert tried.signature != first.signature and placement.trial is not None
    for _ in range(4):  # the new plan does worse than the 100 decisions/s measured before it
        placement.balance(dataclasses.replace(slow, achieved=80.0))
        assert placement.pending is None
    placement.balance(dataclasses.replace(slow, achieved=80.0))
    assert placement.pending is not None and placement.pending.reason.startswith("reverted: plan v2 achieved 80")
    placement.apply()
    assert placement.applied.signature == first.signature and placement.applied.version == 3
    for _ in range(30):  # the same imbalance again: the tried plan stays excluded
        placement.balance(slow).apply()
    assert placement.applied.signature != tried.signature


def test_a_re_plan_that_achieves_as_much_is_kept():
    placement = EmbodiPlacement(pool_of(8), cpu_profiles(8), window=5, gap=0.15, patience=5).apply()
    a = placement.applied.allocation
    slow = StageRates(sim=a.T_sim, gen=a.T_gen, train=a.T_train / 3, achieved=100.0)
    while placement.pending is None:
        placement.balance(slow)
    tried = placement.apply().applied
    for _ in range(10):
        placement.balance(dataclasses.replace(slow, achieved=130.0)).apply()
    assert placement.applied is tried and placement.trial is None


def test_profile_file_is_reused_until_the_machine_or_workload_changes(tmp_path, monkeypatch):
    cfg = config.from_dict({"run": {"output_dir": str(tmp_path)}})
    pool = pool_of(2)
    calls = []

    def fake_profile(pool, cfg, seconds, progress):  # the measuring itself is exercised by `ebrl profile` below
        calls.append(seconds)
        return cpu_profiles(2)

    monkeypatch.setattr(profile_mod, "profile", fake_profile)
    first, path, measured = profile_mod.load_or_profile(pool, cfg, progress=False)
    assert measured and path == tmp_path / "profiles" / "quickstart.json" and calls == [1.0]
    again, _, measured = profile_mod.load_or_profile(pool, cfg, progress=False)
    assert not measured and again.sim == first.sim and len(calls) == 1
    stored = json.loads(path.read_text())
    assert stored["fingerprint"]["cores"] == [0, 1] and "workload" in stored["fingerprint"]
    other = config.from_dict({"run": {"output_dir": str(tmp_path)}, "policy": {"hidden": [32]}})
    _, _, measured = profile_mod.load_or_profile(pool, other, progress=False)
    assert measured  # another policy size: stale
    _, _, measured = profile_mod.load_or_profile(pool_of(1), other, progress=False)
    assert measured  # another machine: stale


def test_ebrl_profile_measures_real_stages_and_prints_an_allocation(tmp_path):
    import subprocess
    import sys

    out = subprocess.run([sys.executable, "-m", "ebrl.cli", "profile", "configs/quickstart.toml", "--seconds", "0.2",
                          "--out", str(tmp_path / "p.json")], capture_output=True, text=True, timeout=180,
                         cwd=str(__import__("pathlib").Path(__file__).resolve().parent.parent))
    assert out.returncode == 0, out.stdout + out.stderr
    assert "profiling 1/" in out.stderr and "Algorithm 1 (" in out.stdout
    stored = Profiles.from_json(json.loads((tmp_path / "p.json").read_text())["profiles"])
    assert all(rate > 0 for table in (stored.sim, stored.gen, stored.train) for rate in table.values())


def test_the_readme_programming_api_example_runs_on_cpu():
    import pathlib
    import subprocess
    import sys

    root = pathlib.Path(__file__).resolve().parent.parent
    out = subprocess.run([sys.executable, "examples/placement.py"], cwd=root, capture_output=True, text=True,
                         timeout=300)
    assert out.returncode == 0, out.stderr[-3000:]
    assert out.stdout.count("iteration ") == 4 and "plan v1" in out.stdout
    assert (root / "examples/placement.py").read_text() in (root / "docs/allocator.md").read_text()  # shown whole


def test_simulation_on_other_hosts_leaves_this_hosts_cores_to_generation_and_training():
    from ebrl.alloc.algorithm import allocate_cpu, exhaustive

    profiles = cpu_profiles(8)
    alone = EmbodiPlacement(pool_of(8), profiles).plan.allocation
    helped = EmbodiPlacement(pool_of(8), profiles, remote_sim=400.0).plan.allocation
    assert helped.s_sim < alone.s_sim and helped.theta > alone.theta  # fewer sim cores here, more throughput
    assert helped.T_sim == pytest.approx(100 * helped.s_sim + 400)  # T_s counts both
    # against the reference: the best split when every candidate's T_s gets the other hosts' 400 decisions/s
    shifted = dataclasses.replace(profiles, sim={k: r + 400 for k, r in profiles.sim.items()})
    assert helped.theta == pytest.approx(exhaustive(shifted, N=8, s_g_min=1, s_t_min=1, cpu=True).theta)
    # a host without a simulator: every core to generation and training, bounded by the other hosts' rate
    remote_only = allocate_cpu(profiles, N=8, remote_sim=400.0, local_sim=False)
    assert (remote_only.E, remote_only.s_sim, remote_only.s_gen + remote_only.s_train) == (0, 0, 8)
    assert remote_only.theta == pytest.approx(min(400, 150 * min(remote_only.s_gen, 4),
                                                  120 * min(remote_only.s_train, 4)))


def test_a_host_without_a_simulator_plans_for_the_others_and_follows_their_capacity():
    placement = EmbodiPlacement(pool_of(4), cpu_profiles(4), window=3, patience=2, local_sim=False).apply()
    plan = placement.applied
    assert plan.cores["sim"] == [] and "sim/0" not in placement.bindings()  # no simulator bound here
    assert sorted(set(plan.cores["gen"]) | set(plan.cores["train"])) == [0, 1, 2, 3]
    assert plan.allocation.theta > 0  # the other hosts' capacity is unknown yet: no limit assumed
    for _ in range(3):  # the other hosts simulate 50 decisions/s: rollout far below training
        placement.balance(StageRates(sim=50.0, gen=300.0, train=400.0, achieved=50.0, remote_sim=50.0))
    assert placement.remote_sim == pytest.approx(50.0)
    assert placement._allocate(placement.profiles).theta == pytest.approx(50.0)  # now planned with their rate


def test_two_cores_with_simulation_elsewhere_share_them_between_generation_and_training():
    from ebrl.alloc.placement import all_shared

    profiles = cpu_profiles(2, saturate=2)
    # every decision simulated elsewhere costs these cores 1/300 + 1/240 s; the time left simulates here
    a = all_shared(profiles, 2, remote_sim=60.0)
    model = 1 / 300 + 1 / 240
    assert a.theta == pytest.approx(60 + (1 - 60 * model) / (model + 1 / 200))
    assert all_shared(profiles, 2, remote_sim=1e9).theta == pytest.approx(1 / model)  # bounded by gen + train
    assert all_shared(profiles, 2, remote_sim=30.0, local_sim=False).theta == pytest.approx(30.0)
