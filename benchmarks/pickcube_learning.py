"""Is PandaPickCube learnable as designed? Success rate against wall-clock of `ebrl up configs/pickcube_cpu.toml`.

    python benchmarks/pickcube_learning.py --minutes 30 --seeds 0,1,2   # real runs, each stopped at 30 minutes
    python benchmarks/pickcube_learning.py --config configs/mjwarp_pickcube.toml --set sim.envs_per_group=32 \
        --set train.batch_size=512 --name mjwarp_cpu_learning     # the MuJoCo Warp batch, on Warp's CPU device

The CPU MuJoCo version of the task (the same model, reward and success check as the MuJoCo Warp batch of
configs/mjwarp_pickcube.toml), or with ``--config configs/mjwarp_pickcube.toml`` that batch itself, trained by a
plain ``ebrl up`` on this machine, one seed after another; a run
ends at 90 % success (``run.target_success``) or when ``--minutes`` pass (Ctrl-C, as a user would). From each
run's ``metrics.csv`` (every finished episode's success and return, with the time its report arrived): per
window of ``--window`` seconds, the success rate and mean return of the episodes that ended in it, and the env
steps so far. Writes ``benchmarks/results/NAME.json`` and ``NAME.png`` (success rate and return against
minutes, every seed).
"""

from __future__ import annotations

import argparse
import csv
import json
import os
import platform
import signal
import statistics
import subprocess
import sys
import textwrap
import time
from pathlib import Path
from typing import Any

ROOT = Path(__file__).resolve().parent.parent
sys.path.insert(0, str(ROOT))

from ebrl import bench  # noqa: E402

RESULTS = ROOT / "benchmarks" / "results"
CONFIG = "configs/pickcube_cpu.toml"


def run(config: str, minutes: float, out_dir: Path, overrides: list[str]) -> Path:
    """``ebrl up config`` until it ends or ``minutes`` pass (then SIGINT, as Ctrl-C); the run's directory."""
    cmd = [sys.executable, "-m", "ebrl.cli", "up", config, "--set", 'viz.rerun="off"',
           "--set", f'run.output_dir="{out_dir}"', *[a for o in overrides for a in ("--set", o)]]
    proc = subprocess.Popen(cmd, cwd=ROOT)
    try:
        proc.wait(timeout=minutes * 60)
    except subprocess.TimeoutExpired:
        proc.send_signal(signal.SIGINT)
        proc.wait(timeout=120)
    return max(out_dir.glob("*/summary.json"), key=lambda p: p.stat().st_mtime).parent


def curve(run_dir: Path, window: float) -> list[dict[str, Any]]:
    """Success rate, mean return and episodes per window, from the first report of the run."""
    episodes: list[tuple[float, float, float]] = []  # (time, success, return)
    steps: list[tuple[float, float]] = []
    with open(run_dir / "metrics.csv") as fh:
        rows = list(csv.DictReader(fh))
    t0 = min(float(r["wall_time"]) for r in rows)
    successes = [r for r in rows if r["key"] == "episode/success"]
    returns = [r for r in rows if r["key"] == "episode/return"]
    for s, r in zip(successes, returns):
        episodes.append((float(s["wall_time"]) - t0, float(s["value"]), float(r["value"])))
    steps = [(float(r["wall_time"]) - t0, float(r["value"])) for r in rows if r["key"] == "sim/env_steps"]
    points = []
    end = max(t for t, *_ in episodes)
    k = 0
    while k * window < end:
        inside = [(s, ret) for t, s, ret in episodes if k * window <= t < (k + 1) * window]
        done = [v for t, v in steps if t < (k + 1) * window]
        if inside:
            points.append({"minute": round((k + 1) * window / 60, 3), "episodes": len(inside),
                           "success_rate": statistics.fmean(s for s, _ in inside),
                           "return_mean": statistics.fmean(r for _, r in inside),
                           "env_steps": done[-1] if done else 0})
        k += 1
    return points


def plot(runs: dict[str, list[dict[str, Any]]], path: Path, title: str) -> None:
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    fig, (top, bottom) = plt.subplots(2, 1, figsize=(7, 5.5), sharex=True)
    for seed, points in runs.items():
        minutes = [p["minute"] for p in points]
        top.plot(minutes, [100 * p["success_rate"] for p in points], label=f"seed {seed}")
        bottom.plot(minutes, [p["return_mean"] for p in points], label=f"seed {seed}")
    top.legend(fontsize=8)
    top.set_ylabel("success rate (%)")
    top.set_ylim(0, 100)
    top.grid(alpha=0.3)
    bottom.set_ylabel("episode return")
    bottom.set_xlabel("minutes since the first report")
    bottom.grid(alpha=0.3)
    top.set_title("\n".join(textwrap.wrap(title, 95, break_long_words=False)), fontsize=8)
    fig.tight_layout()
    fig.savefig(path, dpi=110)


def title(out: dict[str, Any]) -> str:
    return f"PandaPickCube-v0 ({out['config']}), {out['machine']}: {out['command']}"


def _cuda() -> bool:
    import torch

    return torch.cuda.is_available()


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    parser.add_argument("--minutes", type=float, default=30.0, help="the most each run may take")
    parser.add_argument("--seeds", default="0", help="run.seed of each run, in order")
    parser.add_argument("--config", default=CONFIG)
    parser.add_argument("--window", type=float, default=60.0, help="seconds per point of the curve")
    parser.add_argument("--set", dest="overrides", action="append", default=[], help="a config override")
    parser.add_argument("--name", default="pickcube_cpu_learning")
    parser.add_argument("--note", default="", help="recorded with the result (e.g. what else ran)")
    parser.add_argument("--replot", action="store_true", help="only redraw NAME.png from NAME.json")
    args = parser.parse_args()
    if args.replot:
        out = json.loads((RESULTS / f"{args.name}.json").read_text())
        plot({seed: r["curve"] for seed, r in out["runs"].items()}, RESULTS / f"{args.name}.png",
             title(out))
        return
    command = " ".join(["python benchmarks/pickcube_learning.py",
                        *([f"--config {args.config}"] if args.config != CONFIG else []), f"--minutes {args.minutes:g}",
                        f"--seeds {args.seeds}", f"--window {args.window:g}",
                        *[f"--set {o}" for o in args.overrides],
                        *([f"--name {args.name}"] if args.name != "pickcube_cpu_learning" else [])])
    runs: dict[str, Any] = {}
    for seed in args.seeds.split(","):
        run_dir = run(args.config, args.minutes, ROOT / "runs" / "pickcube_learning",
                      [f"run.seed={seed}", *args.overrides])
        summary = json.loads((run_dir / "summary.json").read_text())
        points = curve(run_dir, args.window)
        runs[seed] = {
            "summary": {key: summary.get(key) for key in ("exit_code", "iterations", "wall_s", "env_steps",
                                                          "env_steps_per_s", "episodes", "final_return",
                                                          "target_success", "target_reached")},
            "success_first_window": points[0]["success_rate"], "best_window": max(points, key=lambda p: p[
                "success_rate"]), "curve": points}
        print(json.dumps({"seed": seed, **{k: runs[seed][k] for k in ("success_first_window", "best_window")},
                          "target_reached": summary.get("target_reached")}), flush=True)
    reached = [r["summary"]["target_reached"] for r in runs.values()]
    out = {
        "command": command, "config": args.config, "date": time.strftime("%Y-%m-%d"), "commit": bench.commit(),
        "machine": f"{platform.machine()}, {len(os.sched_getaffinity(0))} cores, "
                   f"{'a CUDA GPU' if _cuda() else 'no GPU'}",
        "note": args.note, "window_s": args.window, "minutes": args.minutes,
        "seeds_reaching_target": sum(r is not None for r in reached),
        "median_s_to_target": statistics.median(r["wall_s"] if r else float("inf") for r in reached),
        "runs": runs,
    }
    RESULTS.mkdir(exist_ok=True)
    (RESULTS / f"{args.name}.json").write_text(json.dumps(out, indent=1) + "\n")
    plot({seed: r["curve"] for seed, r in runs.items()}, RESULTS / f"{args.name}.png", title(out))


if __name__ == "__main__":
    main()
