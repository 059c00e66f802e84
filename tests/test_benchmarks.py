"""Benchmark scripts run: the outside peer, the learning-speed comparison, the soak and the scale-out
benchmarks (short smoke runs; the recorded comparisons are in benchmarks/results/)."""

import json
import subprocess
import sys

import pytest

from helpers import ROOT


@pytest.mark.slow
def test_cleanrl_style_ppo_peer_runs_learns_and_writes_json(tmp_path):
    out = tmp_path / "peer.json"
    proc = subprocess.run([sys.executable, "benchmarks/peers/cleanrl_ppo.py", "--env", "InvertedPendulum-v5",
                           "--num-envs", "8", "--target-return", "900", "--max-seconds", "20", "--seed", "0",
                           "--json", str(out)], cwd=ROOT, capture_output=True, text=True, timeout=180)
    assert proc.returncode == 0, proc.stderr[-3000:]
    result = json.loads(out.read_text())
    summary = result["summary"]
    assert summary["stop_reason"] == "max_seconds" and summary["env_steps"] > 5000 and summary["updates"] >= 2
    assert result["hyperparameters"]["action_chunk"] == 1 and "command" in result


@pytest.mark.slow
def test_learning_speed_benchmark_writes_curves_and_a_plot(tmp_path):
    proc = subprocess.run([sys.executable, "benchmarks/learning_speed.py", "--iterations", "3", "--seeds", "0,1",
                           "--out", str(tmp_path)], cwd=ROOT, capture_output=True, text=True, timeout=600)
    assert proc.returncode == 0, proc.stderr[-3000:]
    result = json.loads((tmp_path / "learning_speed.json").read_text())
    assert set(result["summary"]) == {"ebrl", "colocated"} and result["env_step_budget"] == 3 * 1024 * 4
    assert all(s["env_steps"] > 0 for s in result["summary"].values())
    assert all(set(runs) == {"0", "1"} for runs in result["per_seed"].values())  # one run per mode and seed
    assert result["curves"]["ebrl"] == result["curves_by_seed"]["ebrl"]["0"]
    assert (tmp_path / "learning_speed.png").stat().st_size > 1000


@pytest.mark.slow
def test_two_minute_soak_keeps_every_service_memory_flat(tmp_path):
    out = tmp_path / "soak.json"
    proc = subprocess.run([sys.executable, "benchmarks/soak.py", "--minutes", "2", "--max-growth", "10",
                           "--runs-dir", str(tmp_path / "runs"), "--out", str(out)],
                          cwd=ROOT, capture_output=True, text=True, timeout=700)
    assert proc.returncode == 0, proc.stdout[-3000:] + proc.stderr[-3000:]
    result = json.loads(out.read_text())
    # the log service (TensorBoard on by default) is a long-lived service like the others: its memory counts too
    assert set(result["services"]) == {"sim/0", "gen/0", "train/0", "log/0"} and not result["failed"]
    assert all(row["samples"] >= 60 for row in result["services"].values())


@pytest.mark.slow
def test_scaling_benchmark_measures_a_two_host_run_and_leaves_no_process(tmp_path):
    # The window is 3 s or longer: it ends once rank 0 finished an update in it (--min-updates), so a loaded
    # machine takes longer instead of measuring nothing.
    out = tmp_path / "scaling.json"
    proc = subprocess.run([sys.executable, "benchmarks/scaling.py", "--hosts", "1", "--world-sizes", "1",
                           "--repeat", "1", "--warmup", "0", "--duration", "3", "--min-updates", "1",
                           "--runs-dir", str(tmp_path / "runs"), "--out", str(out)],
                          cwd=ROOT, capture_output=True, text=True, timeout=600)
    assert proc.returncode == 0, proc.stdout[-3000:] + proc.stderr[-3000:]
    result = json.loads(out.read_text())
    (run,) = result["runs"]
    assert run["env_steps_per_s"] > 0 and run["updates_per_s"] > 0 and run["leftover_processes"] == 0
    assert run["window_s"] >= 3
    assert set(run["per_host_env_steps_per_s"]) == {"sim/1"}  # the sim host's stats reached the primary's bus
    assert result["summary"][0]["env_steps_per_s_ratio"] == 1.0 and "command" in result


@pytest.mark.slow
def test_data_parallel_benchmark_writes_curves_for_both_world_sizes_and_a_plot(tmp_path):
    proc = subprocess.run([sys.executable, "benchmarks/data_parallel.py", "--iterations", "3", "--seeds", "0",
                           "--out", str(tmp_path)], cwd=ROOT, capture_output=True, text=True, timeout=600)
    assert proc.returncode == 0, proc.stderr[-3000:]
    result = json.loads((tmp_path / "data_parallel_learning.json").read_text())
    assert set(result["summary"]) == {"1", "2"}
    assert all(s["per_seed"]["0"]["env_steps"] > 0 for s in result["summary"].values())
    assert (tmp_path / "data_parallel_learning.png").stat().st_size > 1000


@pytest.mark.slow
def test_vector_transfer_benchmark_times_every_part_of_a_chunk(tmp_path):
    out = tmp_path / "xfer.json"
    proc = subprocess.run([sys.executable, "benchmarks/vector_transfer.py", "--envs", "4", "--repeat", "2",
                           "--out", str(out)], cwd=ROOT, capture_output=True, text=True, timeout=300)
    assert proc.returncode == 0, proc.stderr[-3000:]
    rows = json.loads(out.read_text())["rows"]
    assert [(r["kind"], r["envs"]) for r in rows] == [("state", 4), ("rgb64", 4)]
    assert all(r["exchange_ms"] > 0 and r["bookkeeping_ms"] > 0 and r["obs_bytes"] > 4 * 4 * r["obs_values"]
               for r in rows)


def test_the_parity_verdict_is_within_three_percent_or_above_also_for_negative_returns():
    import importlib.util
    import math

    spec = importlib.util.spec_from_file_location("learning_parity", ROOT / "benchmarks/learning_parity.py")
    parity = importlib.util.module_from_spec(spec)
    spec.loader.exec_module(parity)

    def verdict(a: list[float], b: list[float]) -> dict:
        runs = {mode: {str(i): {"final_return": r, "best_return": r, "wall_s": wall, "env_steps": 1.0,
                                "to_target_s": None} for i, r in enumerate(returns)}
                for mode, returns, wall in (("ebrl", a, 60.0), ("colocated", b, 100.0))}
        return parity.summarize(runs, ["ebrl", "colocated"])["verdict"]

    assert verdict([970, 960, 980], [1000, 990, 1010])["parity"]  # 0.97x: within 3 %
    assert not verdict([950, 960, 940], [1000, 990, 1010])["parity"]  # 0.95x
    below_zero = verdict([78, -157, 193], [-24, -49, 105])  # returns around 0: no ratio, the difference judges
    assert math.isnan(below_zero["final_return_ratio"]) and below_zero["parity"] and below_zero["faster"]
    assert not verdict([-60, -70, -80], [-24, -49, 105])["parity"]  # more than 3 % below a negative median


def test_the_sweep_bounds_every_ratio_by_what_the_cores_can_step():
    """A ``lat`` point's steps cost their mean latency in CPU time: 2 cores at 4 ms complete at most 500 env
    steps/s, so a best baseline at 400 leaves no mode more than 1.25x (the "cores allow" column)."""
    import importlib.util

    spec = importlib.util.spec_from_file_location("stepping_sweep", ROOT / "benchmarks/stepping_sweep.py")
    sweep = importlib.util.module_from_spec(spec)
    spec.loader.exec_module(sweep)
    steps = {"ebrl": [450.0, 460.0, 470.0], "colocated": [380.0] * 3, "hybrid": [390.0, 400.0, 410.0],
             "async": [200.0] * 3}
    point = {"results": {m: [{"env_steps_per_s": s} for s in runs] for m, runs in steps.items()}}
    top = sweep.ceiling("lat:4:1", sweep.machine_cores("x86_64, 2 usable cores"), point)
    assert top["env_steps_ceiling"] == pytest.approx(500.0)
    assert top["ebrl_of_ceiling"] == pytest.approx(0.92) and top["best_of_ceiling"] == pytest.approx(0.8)
    assert top["ceiling_vs_best"] == pytest.approx(1.25)
    assert sweep.ceiling("halfcheetah", 2, point) == {}  # a named point's step cost is not set


def test_the_pickcube_race_medians_count_a_seed_that_missed_as_its_whole_run():
    """benchmarks/pickcube_race.py: per side, the seeds that reached 90 % and the median updates, where a seed that
    missed counts its whole run (a lower bound); the commands recorded are what a user types."""
    import importlib.util
    from pathlib import Path

    spec = importlib.util.spec_from_file_location("pickcube_race", ROOT / "benchmarks/pickcube_race.py")
    race = importlib.util.module_from_spec(spec)
    spec.loader.exec_module(race)
    runs = [{"side": "peer", "reached": True, "updates": u, "updates_total": u, "seconds": 10.0 * u, "wall_s": 0.0}
            for u in (71, 84, 134)]
    runs += [{"side": "ebrl (ebrl)", "reached": True, "updates": 93, "updates_total": 93, "seconds": 230.0,
              "wall_s": 240.0},
             {"side": "ebrl (ebrl)", "reached": False, "updates": None, "updates_total": 300, "seconds": None,
              "wall_s": 900.0}]
    got = race.medians(runs)
    assert got["peer"] == {"seeds": 3, "reached": 3, "median_updates": 84, "median_seconds": 840.0}
    assert got["ebrl (ebrl)"]["reached"] == 1 and got["ebrl (ebrl)"]["median_updates"] == 196.5
    out = Path("/scratch/ebrl-3")
    shown = race.shown(race.ebrl_command(3, "ebrl", False, out, []), f'run.output_dir="{out}"')
    assert shown.startswith("ebrl up configs/mjwarp_pickcube.toml --set sim.envs_per_group=64")
    assert "--set run.seed=3" in shown and "scratch" not in shown
    peer = race.shown(race.peer_command(3, False, 900, Path("/scratch/p.json")), "--json")
    assert peer == "python benchmarks/peers/mjwarp_ppo.py --device cpu --num-envs 128 --seed 3 --max-seconds 900"


def test_the_gpu_race_summary_gives_medians_and_issue_51_s_ratios(tmp_path):
    """check.sh mjwarp_race's verdict from the files it leaves: each side's seconds to 90 % per seed (a seed that
    did not reach it has none), medians, and the two ratios of the acceptance."""
    def ebrl(folder: str, seed: int, in_run: float | None, rate: float) -> None:
        run = tmp_path / f"{folder}-s{seed}" / "mjwarp_pickcube-20261128-120000"
        run.mkdir(parents=True)
        reached = None if in_run is None else {"iteration": 40, "wall_s": in_run, "success_rate": 0.9}
        (run / "summary.json").write_text(json.dumps({"target_reached": reached, "env_steps_per_s": rate}))

    for seed, in_run, rate in ((0, 20.0, 200_000.0), (1, 24.0, 190_000.0), (2, None, 210_000.0)):
        ebrl("mjwarp-race", seed, in_run, rate)
    ebrl("mjwarp-race-separate", 0, 36.0, 90_000.0)
    for seed, to90 in ((0, 31.0), (1, 34.0), (2, 33.0)):
        (tmp_path / f"peer_mjwarp_ppo_s{seed}.json").write_text(json.dumps({"summary": {
            "target_reached": {"wall_s": to90}, "rollout_env_steps_per_s": 215_000.0}}))
    times = ["ebrl 0 24.5", "peer 0 33.0", "ebrl 1 27.5", "peer 1 36.0", "ebrl 2 120.3", "peer 2 35.0",
             "ebrl_separate 0 48.0"]
    (tmp_path / "times.txt").write_text("\n".join(times) + "\n")
    out = subprocess.run([sys.executable, str(ROOT / "benchmarks" / "gpu" / "race_summary.py"), str(tmp_path),
                          "--seeds", "0 1 2", "--json", str(tmp_path / "verdict.json")],
                         capture_output=True, text=True, check=True).stdout
    verdict = json.loads((tmp_path / "verdict.json").read_text())
    ebrl_m, peer_m = verdict["medians"]["ebrl"], verdict["medians"]["peer"]
    assert ebrl_m["whole"] == 26.0 and ebrl_m["reached"] == 2 and ebrl_m["in_run"] == 22.0  # seed 2 never got there
    assert peer_m["whole"] == 35.0 and peer_m["rate"] == 215_000.0
    assert verdict["ebrl"]["whole_ratio"] == pytest.approx(26.0 / 35.0) and verdict["ebrl"]["whole_holds"]
    assert verdict["ebrl"]["rate_ratio"] == pytest.approx(200_000 / 215_000) and verdict["ebrl"]["rate_holds"]
    assert not verdict["ebrl_separate"]["whole_holds"] and not verdict["ebrl_separate"]["rate_holds"]
    assert "ebrl / peer: whole command 0.743x (acceptance <= 0.75: holds)" in out, out
