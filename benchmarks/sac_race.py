"""EBRL's SAC against Stable-Baselines3's, seed by seed: return against env steps and against wall-clock seconds.

    pip install stable-baselines3==2.9.2      # the peer's, a benchmark dependency
    python benchmarks/sac_race.py --env Pendulum-v1 --seeds 0,1,2
    python benchmarks/sac_race.py --env HalfCheetah-v5 --seeds 0,1,2 --total-steps 50000

Each seed runs the peer (``benchmarks/peers/sb3_sac.py``: one env, an env step then a gradient step, rl-zoo3's
hyperparameters) and ``ebrl up`` of the task's config (:data:`TASKS`: the same hyperparameters, ``run.seed`` set,
no target so that both sides spend the same env-step budget), one run at a time. Both clocks start when the
command starts, imports and start-up included.

The comparison, as issue 53 states it: the peer's median final return R (the mean of its last 20 episodes at the
budget); each side's seconds to first reach R; EBRL's median seconds over the peer's. A run that never reaches R
counts as its whole run (a lower bound: the median then says "at least"). Writes ``--json`` (default
``benchmarks/results/sac_race_<env>.json``: every run's command, curve and times) and a plot of the curves beside
it (``.png``).
"""

from __future__ import annotations

import argparse
import csv
import json
import os
import platform
import shlex
import statistics
import subprocess
import sys
import tempfile
import time
from pathlib import Path

ROOT = Path(__file__).resolve().parent.parent
sys.path.insert(0, str(ROOT))

from ebrl import bench  # noqa: E402
from ebrl.config import load  # noqa: E402

# env -> (EBRL's config, env steps of rl-zoo3's budget we race over by default)
TASKS = {"Pendulum-v1": ("configs/sac_pendulum.toml", 20_000), "HalfCheetah-v5": ("configs/sac_halfcheetah.toml",
                                                                                   50_000)}


def ebrl_curve(run_dir: Path, started: float) -> list[dict[str, float]]:
    """From a run's ``metrics.csv``: each report of ``train/episode_return_mean`` with the env steps training
    had taken (``train/env_steps``) and the seconds since the command started."""
    steps, curve = 0.0, []
    with open(run_dir / "metrics.csv") as fh:
        for row in csv.DictReader(fh):
            if row["key"] == "train/env_steps":
                steps = float(row["value"])
            elif row["key"] == "train/episode_return_mean" and row["value"] not in ("", "nan"):
                curve.append({"env_steps": steps, "seconds": float(row["wall_time"]) - started,
                              "return_mean": float(row["value"])})
    return curve


def run_ebrl(env: str, seed: int, total: int, sets: list[str], scratch: Path) -> dict:
    config, _ = TASKS[env]
    cfg = load(ROOT / config, sets)
    batch = cfg.train.batch_size * cfg.policy.chunk  # env steps an update takes in: updates = budget / batch
    argv = ["ebrl", "up", config, "--set", f"run.seed={seed}", "--set", f"run.iterations={total // batch}",
            "--set", "run.target_return=", "--set", 'viz.rerun="off"', *[a for s in sets for a in ("--set", s)]]
    out = scratch / f"ebrl-{seed}"
    started = time.time()
    proc = subprocess.run([sys.executable, "-m", "ebrl.cli", *argv[1:], "--set", f'run.output_dir="{out}"'],
                          cwd=ROOT, stdout=subprocess.DEVNULL, stderr=subprocess.DEVNULL)
    run_dir = sorted(out.glob("*/summary.json"))[-1].parent
    summary = json.loads((run_dir / "summary.json").read_text())
    curve = ebrl_curve(run_dir, started)
    return {"side": "ebrl", "seed": seed, "command": shlex.join(argv), "exit_code": proc.returncode,
            "wall_s": round(time.time() - started, 1), "env_steps": summary.get("env_steps"),
            "final_return_mean": curve[-1]["return_mean"] if curve else None, "curve": curve}


def run_peer(env: str, seed: int, total: int, scratch: Path) -> dict:
    out = scratch / f"peer-{seed}.json"
    argv = ["python", "benchmarks/peers/sb3_sac.py", "--env", env, "--seed", str(seed), "--total-steps", str(total)]
    started = time.time()
    proc = subprocess.run([sys.executable, *argv[1:], "--json", str(out)], cwd=ROOT, stdout=subprocess.DEVNULL,
                          stderr=subprocess.DEVNULL)
    summary = json.loads(out.read_text()) if out.exists() else {}
    return {"side": "peer", "seed": seed, "command": shlex.join(argv), "exit_code": proc.returncode,
            "wall_s": round(time.time() - started, 1), "env_steps": summary.get("env_steps"),
            "final_return_mean": summary.get("final_return_mean"), "curve": summary.get("curve", [])}


def first_reach(run: dict, level: float) -> tuple[bool, float, float]:
    """(reached, seconds, env steps) of the first report at or above ``level``; else the whole run."""
    for point in run["curve"]:
        if point["return_mean"] >= level:
            return True, point["seconds"], point["env_steps"]
    return False, run["wall_s"], float(run["env_steps"] or 0)


def compare(runs: list[dict]) -> dict:
    peer = [r for r in runs if r["side"] == "peer" and r["final_return_mean"] is not None]
    if not peer:
        return {}
    level = statistics.median(r["final_return_mean"] for r in peer)
    out: dict = {"peer_median_final_return": level}
    for side in ("ebrl", "peer"):
        rows = [r for r in runs if r["side"] == side]
        reach = [first_reach(r, level) for r in rows]
        out[side] = {"seeds": len(rows), "reached": sum(ok for ok, _, _ in reach),
                     "median_seconds_to_level": statistics.median(s for _, s, _ in reach),
                     "median_env_steps_to_level": statistics.median(n for _, _, n in reach),
                     "median_final_return": statistics.median(r["final_return_mean"] for r in rows
                                                              if r["final_return_mean"] is not None)}
    out["seconds_ratio"] = out["ebrl"]["median_seconds_to_level"] / out["peer"]["median_seconds_to_level"]
    return out


def plot(runs: list[dict], env: str, path: Path) -> None:
    import matplotlib
    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    fig, axes = plt.subplots(1, 2, figsize=(11, 4))
    colours = {"ebrl": "tab:blue", "peer": "tab:orange"}
    for run in runs:
        curve = run["curve"]
        label = f"{'EBRL' if run['side'] == 'ebrl' else 'SB3'} seed {run['seed']}"
        for ax, x in zip(axes, ("env_steps", "seconds")):
            ax.plot([p[x] for p in curve], [p["return_mean"] for p in curve], color=colours[run["side"]],
                    alpha=0.8, label=label)
    for ax, x in zip(axes, ("env steps", "wall-clock seconds (whole command)")):
        ax.set_xlabel(x)
        ax.set_ylabel("mean return, last 20 episodes")
        ax.grid(alpha=0.3)
    axes[0].legend(fontsize=7)
    fig.suptitle(f"SAC on {env}: EBRL (blue) and Stable-Baselines3 (orange), 2 CPU cores")
    fig.tight_layout()
    fig.savefig(path, dpi=90)


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    parser.add_argument("--env", default="Pendulum-v1", choices=sorted(TASKS))
    parser.add_argument("--seeds", default="0,1,2")
    parser.add_argument("--sides", default="ebrl,peer")
    parser.add_argument("--total-steps", type=int, default=0, help="env steps per run (0: the task's default)")
    parser.add_argument("--set", action="append", default=[], metavar="SECTION.KEY=VALUE", help="for EBRL's runs")
    parser.add_argument("--json", default=None)
    parser.add_argument("--merge", default=None, metavar="JSON", help="an earlier result: its runs are kept, but "
                        "for the sides and seeds run now (a run disturbed by other work, run again alone)")
    args = parser.parse_args()
    total = args.total_steps or TASKS[args.env][1]
    sides = [s.strip() for s in args.sides.split(",") if s.strip()]
    path = Path(args.json or ROOT / f"benchmarks/results/sac_race_{args.env.split('-')[0].lower()}.json")
    runs = []
    with tempfile.TemporaryDirectory(prefix="sac-race-") as scratch:
        for seed in (int(s) for s in args.seeds.split(",")):
            for side in sides:
                row = run_ebrl(args.env, seed, total, args.set, Path(scratch)) if side == "ebrl" else \
                    run_peer(args.env, seed, total, Path(scratch))
                runs.append(row)
                print(f"{side:5s} seed {seed}: final mean return {row['final_return_mean']}, {row['wall_s']} s "
                      f"(exit {row['exit_code']})", flush=True)
    if args.merge:
        now = {(r["side"], r["seed"]) for r in runs}
        earlier = json.loads(Path(args.merge).read_text())
        runs = [r for r in earlier["runs"] if (r["side"], r["seed"]) not in now] + runs
        runs.sort(key=lambda r: (r["seed"], r["side"]))
    result = {"command": "python benchmarks/sac_race.py " + " ".join(sys.argv[1:]), "commit": bench.commit(),
              "date": time.strftime("%Y-%m-%d"), "env": args.env, "total_steps": total,
              "machine": f"{platform.machine()}, {len(os.sched_getaffinity(0))} usable cores",
              "compare": compare(runs), "runs": runs}
    if args.merge:
        result["merged_into"] = earlier["command"]  # the runs this one replaced some of
    path.write_text(json.dumps(result, indent=1) + "\n")
    plot(runs, args.env, path.with_suffix(".png"))
    print(json.dumps(result["compare"], indent=1))


if __name__ == "__main__":
    main()
