"""Every execution mode runs end to end; the staleness bound holds; robosuite Lift in every mode (slow)."""

import pytest

from helpers import run_collecting_stats

MODES = ["ebrl", "colocated", "hybrid", "async"]


def staleness_seen(stats) -> int:
    """Largest lag (in policy versions) of any decision that reached a PPO update."""
    hist = stats["train/0"][-1]
    lags = [int(k.rsplit("_", 1)[1]) for k, v in hist.items() if k.startswith("train/staleness_hist_") and v > 0]
    return max(lags)


# The fast suite runs the product end to end; every mode's logic runs in one process in test_pipeline.py
E2E_MODES = ["ebrl", *(pytest.param(mode, marks=pytest.mark.slow) for mode in MODES[1:])]


@pytest.mark.parametrize("mode", E2E_MODES)
def test_mode_runs_and_keeps_the_staleness_bound(tmp_path, mode):
    # async trains on stale data with the interpolated proximal log-probs, the others recompute them
    prox = 'algo.prox_logp="interpolate"' if mode == "async" else 'algo.prox_logp="recompute"'
    code, out, stats = run_collecting_stats(tmp_path / "runs", "configs/quickstart.toml", "run.iterations=4",
                                            f"run.mode={mode}", "algo.max_staleness=1", prox, run=f"mode-{mode}")
    assert code == 0, out
    last = stats["train/0"][-1]
    assert last["train/policy_version"] == 4
    assert all(m["train/staleness_max"] <= 1 for m in stats["train/0"] if "train/staleness_max" in m)
    if mode in ("colocated", "hybrid"):  # rollout -> train barrier: every update is on-policy
        assert staleness_seen(stats) == 0 and last.get("train/stale_dropped", 0) == 0
    else:
        assert staleness_seen(stats) <= 1


def test_core_rebinding_with_a_heavy_tailed_step_latency(tmp_path):
    code, out, stats = run_collecting_stats(
        tmp_path / "runs", "configs/quickstart.toml", "run.iterations=2", "sim.core_rebinding=true",
        "env.latency=\"lognormal\"", "env.latency_mean_ms=1.0", "env.latency_sigma=0.8", "train.batch_size=256",
        run="rebind")
    assert code == 0, out
    sim = stats["sim/0"][-1]
    busy = [v for k, v in sim.items() if k.startswith("sim/core") and k.endswith("_busy_s")]
    assert busy and sum(busy) > 0  # steps were dispatched core by core
    assert sim["sim/chunk_latency_p99_ms"] >= sim["sim/chunk_latency_p50_ms"] > 1.0  # the latency was added
    used = [m["sim/env_cores_used"] for m in stats["sim/0"] if "sim/env_cores_used" in m]
    assert used and all(0 < u <= 1.05 for u in used)  # single-threaded envs: at most one core each
    logs = out + "".join(p.read_text() for p in (tmp_path / "runs").glob("*/logs/*.log"))
    assert "never retrieved" not in logs and "InvalidStateError" not in logs  # stopping with rebinding on: clean


@pytest.mark.slow
@pytest.mark.parametrize("mode", MODES)
def test_robosuite_lift_runs_in_every_mode(tmp_path, mode):
    code, out, stats = run_collecting_stats(
        tmp_path / "runs", "configs/robosuite_lift.toml", "run.iterations=2", "train.batch_size=64",
        "env.max_episode_steps=40", f"run.mode={mode}", run=f"lift-{mode}", timeout=400)
    assert code == 0, out
    assert stats["train/0"][-1]["train/policy_version"] == 2
    assert "sim/success_rate" in stats["sim/0"][-1]  # robosuite's own success check is exported


@pytest.mark.slow
def test_ebrl_bench_prints_the_table_and_writes_json(tmp_path):
    import json
    import subprocess
    import sys

    from helpers import ROOT

    out_json = tmp_path / "bench.json"
    proc = subprocess.run([sys.executable, "-m", "ebrl.cli", "bench", "configs/quickstart.toml", "--modes",
                           "ebrl,colocated,async", "--duration", "4", "--json", str(out_json), "--raw-seconds", "2",
                           "--set", f"run.output_dir={json.dumps(str(tmp_path / 'runs'))}"],
                          cwd=ROOT, capture_output=True, text=True, timeout=850)
    assert proc.returncode == 0, proc.stderr
    assert "vs best baseline" in proc.stdout and "colocated" in proc.stdout and "(best)" in proc.stdout
    results = json.loads(out_json.read_text())["results"]
    assert set(results) == {"ebrl", "colocated", "async"}
    assert all(r[0]["env_steps_per_s"] > 0 for r in results.values())
    # the physical limit: raw capacity of the cores each mode's simulation holds (async holds half of them)
    assert "sim eff" in proc.stdout and "raw simulator capacity" in proc.stderr
    ebrl, asy = results["ebrl"][0], results["async"][0]
    assert ebrl["raw_env_steps_per_s"] > 0 and 0 < ebrl["sim_efficiency"] < 1.5
    assert len(asy["sim_cores"]) <= len(ebrl["sim_cores"])


@pytest.mark.slow
def test_ebrl_bench_measures_a_run_renamed_with_set(tmp_path):
    """`ebrl bench CONFIG --set run.name=X` watches run X (it once watched the name bench chose, waited 300 s and
    failed while the run trained; tests/test_testing.py covers the name resolution fast)."""
    import json
    import subprocess
    import sys

    from helpers import ROOT

    out_json = tmp_path / "bench.json"
    proc = subprocess.run([sys.executable, "-m", "ebrl.cli", "bench", "configs/quickstart.toml", "--modes", "ebrl",
                           "--duration", "3", "--raw-seconds", "0", "--json", str(out_json), "--set", "run.name=renamed",
                           "--set", f"run.output_dir={json.dumps(str(tmp_path / 'runs'))}"],
                          cwd=ROOT, capture_output=True, text=True, timeout=600)
    assert proc.returncode == 0, proc.stderr
    (result,) = json.loads(out_json.read_text())["results"]["ebrl"]
    assert result["env_steps_per_s"] > 0 and result["traj_per_s"] > 0
    assert [p.name.split("-")[0] for p in (tmp_path / "runs").iterdir()] == ["renamed"]


def test_ablations_flip_each_mechanism_from_what_ebrl_runs_with_the_config():
    from ebrl.bench import ablation_variants, base_mode

    # The quickstart leaves the allocator off, so its variant switches it on; core rebinding is "auto", so it
    # is switched off and forced on; overlap is switched off. Its one group has nothing to pipeline.
    assert ablation_variants("configs/quickstart.toml", []) == {
        "ebrl+allocator": ["alloc.enabled=true"],
        "ebrl-no_overlap": ["train.overlap=false"],
        "ebrl-no_core_rebinding": ["sim.core_rebinding=false"],
        "ebrl+core_rebinding": ["sim.core_rebinding=true"],
        "ebrl+vectorized": ["sim.vectorized=true"],  # "auto" leaves a CPU env one process per env
    }
    assert "ebrl+vectorized" not in ablation_variants("configs/grpo_pendulum.toml", [])  # refused with GRPO
    assert "ebrl-no_vectorized" in ablation_variants("configs/quickstart.toml", ["sim.vectorized=true"])
    assert "ebrl+core_rebinding" not in ablation_variants("configs/quickstart.toml", ["sim.core_rebinding=true"])
    two = ["sim.groups=2", "sim.envs_per_group=4"]
    assert ablation_variants("configs/quickstart.toml", two)["ebrl-no_group_pipeline"] == ["sim.group_pipeline=false"]
    assert "ebrl+group_pipeline" not in ablation_variants("configs/quickstart.toml", [])  # one group: no variant
    lift = ablation_variants("configs/robosuite_lift.toml", ["alloc.enabled=true"])
    assert "ebrl-no_allocator" in lift and "ebrl-no_core_rebinding" in lift and "ebrl+vectorized" not in lift
    assert [base_mode(v) for v in ("ebrl", "ebrl-no_overlap", "ebrl+allocator", "colocated")] == [
        "ebrl", "ebrl", "ebrl", "colocated"]
    # rendering only what is read is ebrl's: a camera config gets the ablation, a state config none
    assert ablation_variants("configs/robosuite_lift_rgb.toml", [])["ebrl-no_lazy_render"] == ["sim.lazy_render=false"]
    assert not any("lazy_render" in v for v in ablation_variants("configs/robosuite_lift.toml", []))


def test_the_bench_table_says_inf_when_no_baseline_finished_a_trajectory():
    from ebrl.bench import table

    def result(traj: float, steps: float) -> dict:
        return dict(traj_per_s=traj, env_steps_per_s=steps, chunk_latency_avg_ms=1.0, chunk_latency_p50_ms=1.0,
                    chunk_latency_p99_ms=1.0, idle_sim=0.0, idle_gen=0.0, idle_train=0.0, useful_work_utilisation=1.0)

    rows = table({"ebrl": [result(1.5, 64.0)], "hybrid": [result(0.0, 13.0)]}).splitlines()
    assert rows[1].split()[-1] == "inf" and rows[2].split()[-2:] == ["-", "(best)"]


def test_bench_variants_name_their_mode_and_carry_their_overrides(capsys):
    from ebrl.bench import main, parse_variant

    assert parse_variant("hybrid+vectorized=sim.vectorized=true") == ("hybrid+vectorized", ["sim.vectorized=true"])
    assert parse_variant("ebrl-x=sim.groups=4,train.batch_size=256") == ("ebrl-x", ["sim.groups=4",
                                                                                   "train.batch_size=256"])
    for bad in ("vectorized=sim.vectorized=true", "hybrid=sim.vectorized=true", "hybrid+v"):
        with pytest.raises(ValueError, match="LABEL a mode followed by"):
            parse_variant(bad)
    assert main("configs/quickstart.toml", "ebrl", False, 1.0, 1, "", [], extra=["turbo=sim.groups=1"]) == 2
    assert "--variant 'turbo=sim.groups=1'" in capsys.readouterr().err


@pytest.mark.slow
def test_ebrl_bench_ablations_measure_a_number_of_trajectories(tmp_path):
    import json
    import subprocess
    import sys

    from helpers import ROOT

    out_json = tmp_path / "bench.json"
    proc = subprocess.run([sys.executable, "-m", "ebrl.cli", "bench", "configs/quickstart.toml", "--modes", "ebrl",
                           "--ablations", "--trajectories", "24", "--json", str(out_json), "--raw-seconds", "0",
                           "--set", "alloc.profile_seconds=0.2",
                           "--set", f"run.output_dir={json.dumps(str(tmp_path / 'runs'))}"],
                          cwd=ROOT, capture_output=True, text=True, timeout=600)
    assert proc.returncode == 0, proc.stderr
    data = json.loads(out_json.read_text())
    assert set(data["results"]) == {"ebrl", "ebrl+allocator", "ebrl-no_overlap", "ebrl-no_core_rebinding",
                                    "ebrl+core_rebinding", "ebrl+vectorized"}
    assert data["trajectories"] == 24 and data["variants"]["ebrl+allocator"][-1] == "alloc.enabled=true"
    for variant, (result,) in data["results"].items():
        # the window ends at the first report with 24 more segments; stats come once a second
        assert result["trajectories"] >= 24 and result["traj_per_s"] > 0, variant
    assert "ebrl+allocator" in proc.stdout


@pytest.mark.slow
def test_the_w1_benchmark_config_runs_every_mode_in_one_command(tmp_path):
    """Issue acceptance: `ebrl bench configs/bench_lift.toml --modes ebrl,colocated,hybrid,async` prints the table
    and writes the JSON (here with short windows)."""
    import json
    import subprocess
    import sys

    from helpers import ROOT

    out_json = tmp_path / "w1.json"
    proc = subprocess.run([sys.executable, "-m", "ebrl.cli", "bench", "configs/bench_lift.toml", "--modes",
                           "ebrl,colocated,hybrid,async", "--duration", "5", "--raw-seconds", "1", "--json",
                           str(out_json), "--set", f"run.output_dir={json.dumps(str(tmp_path / 'runs'))}"],
                          cwd=ROOT, capture_output=True, text=True, timeout=900)
    assert proc.returncode == 0, proc.stderr
    results = json.loads(out_json.read_text())["results"]
    assert set(results) == {"ebrl", "colocated", "hybrid", "async"}
    assert all(r[0]["env_steps_per_s"] > 0 and r[0]["sim_efficiency"] > 0 for r in results.values())
    assert "(best)" in proc.stdout


def test_only_ebrl_renders_just_the_observations_it_reads_and_the_switch_overrides_the_mode():
    """RLinf's LIBERO env renders its cameras at every step of a chunk; the baseline modes do as it does,
    ebrl renders only a chunk's last observation (sim.lazy_render overrides either). A worker's env that
    renders on demand (tests/user_envs.py: its observation counts its renders) shows which happened."""
    import asyncio
    import dataclasses

    import numpy as np

    from ebrl import config
    from ebrl.envs import EnvSpec, EnvWorker
    from ebrl.sched.modes import resolve

    for mode, lazy in (("ebrl", True), ("colocated", False), ("hybrid", False), ("async", False)):
        assert resolve(config.load("configs/quickstart.toml", [f"run.mode={mode}"])).lazy_render is lazy
        flipped = config.load("configs/quickstart.toml", [f"run.mode={mode}", f"sim.lazy_render={str(not lazy).lower()}"])
        assert resolve(flipped).lazy_render is (not lazy)

    async def renders_per_chunk(lazy: bool) -> list[float]:
        worker = EnvWorker(dataclasses.replace(EnvSpec("user_envs:CountsRenders-v0"), lazy_render=lazy), seed=0)
        try:
            await worker.reset()
            return [float((await worker.chunk(np.zeros((4, 1), np.float32))).next_obs[0]) for _ in range(3)]
        finally:
            worker.close()

    assert asyncio.run(renders_per_chunk(True)) == [2.0, 3.0, 4.0]  # the reset's, then one per chunk
    assert asyncio.run(renders_per_chunk(False)) == [5.0, 9.0, 13.0]  # every step's
