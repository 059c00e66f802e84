"""Is PandaPickCube learnable as designed? Success rate against wall-clock of `ebrl up configs/pickcube_cpu.toml`.

    python benchmarks/pickcube_learning.py --minutes 30            # a real run, stopped after 30 minutes
    python benchmarks/pickcube_learning.py --run-dir runs/pickcube_cpu-...  # record a run made by hand

The CPU MuJoCo version of the task (the same model, reward and success check as the MuJoCo Warp batch of
configs/mjwarp_pickcube.toml) trained by a plain ``ebrl up`` on this machine; the run ends at 90 % success or
when ``--minutes`` pass (Ctrl-C, as a user would). From the run's ``metrics.csv`` (every finished episode's
success and return, with the time its report arrived): per window of ``--window`` seconds, the success rate
and mean return of the episodes that ended in it, and the env steps so far. Writes
``benchmarks/results/NAME.json`` and ``NAME.png`` (success rate and return against minutes).
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
import time
from pathlib import Path
from typing import Any

ROOT = Path(__file__).resolve().parent.parent
sys.path.insert(0, str(ROOT))

from ebrl import bench  # noqa: E402

RESULTS = ROOT / "benchmarks" / "results"
CONFIG = "configs/pickcube_cpu.toml"


def run(minutes: float, out_dir: Path, overrides: list[str]) -> Path:
    """``ebrl up CONFIG`` until it ends or ``minutes`` pass (then SIGINT, as Ctrl-C); the run's directory."""
    cmd = [sys.executable, "-m", "ebrl.cli", "up", CONFIG, "--set", 'viz.rerun="off"',
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
            points.append({"minute": round((k + 1) * window / 60, 2), "episodes": len(inside),
                           "success_rate": statistics.fmean(s for s, _ in inside),
                           "return_mean": statistics.fmean(r for _, r in inside),
                           "env_steps": done[-1] if done else 0})
        k += 1
    return points


def plot(points: list[dict[str, Any]], path: Path, title: str) -> None:
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    fig, (top, bottom) = plt.subplots(2, 1, figsize=(7, 5.5), sharex=True)
    minutes = [p["minute"] for p in points]
    top.plot(minutes, [100 * p["success_rate"] for p in points], color="tab:green")
    top.set_ylabel("success rate (%)")
    top.set_ylim(0, 100)
    top.grid(alpha=0.3)
    bottom.plot(minutes, [p["return_mean"] for p in points], color="tab:blue")
    bottom.set_ylabel("episode return")
    bottom.set_xlabel("minutes since the first report")
    bottom.grid(alpha=0.3)
    top.set_title(title, fontsize=10)
    fig.tight_layout()
    fig.savefig(path, dpi=110)


def _cuda() -> bool:
    import torch

    return torch.cuda.is_available()


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    parser.add_argument("--minutes", type=float, default=30.0)
    parser.add_argument("--run-dir", type=Path, help="record this finished run instead of starting one")
    parser.add_argument("--window", type=float, default=60.0, help="seconds per point of the curve")
    parser.add_argument("--set", dest="overrides", action="append", default=[], help="a config override")
    parser.add_argument("--name", default="pickcube_cpu_learning")
    parser.add_argument("--note", default="", help="recorded with the result (e.g. what else ran)")
    parser.add_argument("--command", default="", help="with --run-dir: the command that made the run")
    args = parser.parse_args()
    if args.run_dir is None:
        run_dir = run(args.minutes, ROOT / "runs" / "pickcube_learning", args.overrides)
        command = " ".join(["python benchmarks/pickcube_learning.py", f"--minutes {args.minutes:g}",
                            *[f"--set {o}" for o in args.overrides]])
    else:
        run_dir, command = args.run_dir, args.command or f"ebrl up {CONFIG} (recorded from {args.run_dir.name})"
    summary = json.loads((run_dir / "summary.json").read_text())
    points = curve(run_dir, args.window)
    first, last = points[:3], points[-3:]
    out = {
        "command": command, "config": CONFIG, "date": time.strftime("%Y-%m-%d"),
        "machine": f"{platform.machine()}, {len(os.sched_getaffinity(0))} cores, no GPU" if not _cuda() else
                   f"{platform.machine()}, {len(os.sched_getaffinity(0))} cores, with a CUDA GPU",
        "commit": bench.commit(), "note": args.note, "window_s": args.window,
        "summary": {key: summary.get(key) for key in ("exit_code", "iterations", "wall_s", "env_steps",
                                                      "env_steps_per_s", "episodes", "final_return",
                                                      "target_success", "target_reached")},
        "success_first_3_windows": statistics.fmean(p["success_rate"] for p in first),
        "success_last_3_windows": statistics.fmean(p["success_rate"] for p in last),
        "best_window": max(points, key=lambda p: p["success_rate"]),
        "curve": points,
    }
    RESULTS.mkdir(exist_ok=True)
    (RESULTS / f"{args.name}.json").write_text(json.dumps(out, indent=1) + "\n")
    plot(points, RESULTS / f"{args.name}.png",
         f"PandaPickCube-v0, CPU MuJoCo, {out['machine']}\n{command}")
    print(json.dumps({k: out[k] for k in ("success_first_3_windows", "success_last_3_windows", "best_window")}))


if __name__ == "__main__":
    main()
