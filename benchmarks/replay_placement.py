"""Where the replay runs: in training's process (``run.processes = "auto"``) or in a process of its own.

    python benchmarks/replay_placement.py --rounds 3
    python benchmarks/replay_placement.py --rounds 3 --baseline /tmp/ebrl-a1aec31   # + a checkout from before

Each round runs ``ebrl up configs/sac_pendulum.toml`` (no target: the same iterations each time) once per arm,
one run at a time, the arms interleaved: ``shared`` (the default: the replay shares train's process, its messages
by reference), ``separate`` (``run.processes = []``: the replay alone, its messages over the bus) and, with
``--baseline``, the same command in another checkout (one from before the replay was a service: the replay then
lived inside train). Reported per run: the whole command's seconds, the run's env steps per second from its
first to its last report, training's mean seconds per update and the seconds it waited for the replay
(``train/replay_wait_s``). Writes ``--json`` (default ``benchmarks/results/replay_placement.json``).
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
ARMS = {"shared": [], "separate": ["run.processes=[]"]}


def read_run(run_dir: Path) -> dict[str, float]:
    """From a run's ``metrics.csv``: env steps per second between the first and the last env-step report,
    training's mean update seconds and the seconds it waited for the replay."""
    steps: list[tuple[float, float]] = []
    updates: list[float] = []
    wait = 0.0
    with open(run_dir / "metrics.csv") as fh:
        for row in csv.DictReader(fh):
            if row["key"] == "train/env_steps":
                steps.append((float(row["wall_time"]), float(row["value"])))
            elif row["key"] == "train/update_s":
                updates.append(float(row["value"]))
            elif row["key"] == "train/replay_wait_s":
                wait = float(row["value"])
    (t0, s0), (t1, s1) = steps[0], steps[-1]
    return {"env_steps_per_s": (s1 - s0) / max(t1 - t0, 1e-9), "update_s_mean": statistics.fmean(updates),
            "replay_wait_s": wait, "env_steps": s1}


def run_once(arm: str, sets: list[str], repo: Path, iterations: int, scratch: Path) -> dict:
    out = scratch / f"{arm}-{time.monotonic_ns()}"
    argv = ["ebrl", "up", "configs/sac_pendulum.toml", "--set", f"run.iterations={iterations}", "--set",
            "run.target_return=", "--set", 'viz.rerun="off"', *[a for s in sets for a in ("--set", s)]]
    env = {**os.environ, "PYTHONPATH": str(repo)}
    started = time.time()
    proc = subprocess.run([sys.executable, "-m", "ebrl.cli", *argv[1:], "--set", f'run.output_dir="{out}"'],
                          cwd=repo, env=env, stdout=subprocess.DEVNULL, stderr=subprocess.DEVNULL)
    wall = time.time() - started
    run_dir = sorted(out.glob("*/summary.json"))[-1].parent
    return {"arm": arm, "command": shlex.join(argv), "repo": str(repo), "exit_code": proc.returncode,
            "wall_s": round(wall, 2), **read_run(run_dir)}


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    parser.add_argument("--rounds", type=int, default=3)
    parser.add_argument("--iterations", type=int, default=150)
    parser.add_argument("--baseline", type=Path, help="another checkout to run the same command in (arm 'baseline')")
    parser.add_argument("--json", type=Path, default=ROOT / "benchmarks" / "results" / "replay_placement.json")
    args = parser.parse_args()
    arms = [(arm, sets, ROOT) for arm, sets in ARMS.items()]
    if args.baseline:
        arms.append(("baseline", [], args.baseline.resolve()))
    runs = []
    with tempfile.TemporaryDirectory() as scratch:
        for round_ in range(args.rounds):
            for arm, sets, repo in arms:
                runs.append({"round": round_, **run_once(arm, sets, repo, args.iterations, Path(scratch))})
                print(json.dumps(runs[-1]), flush=True)
    summary = {arm: {key: statistics.median(r[key] for r in runs if r["arm"] == arm)
                     for key in ("wall_s", "env_steps_per_s", "update_s_mean", "replay_wait_s")}
               for arm, _, _ in arms}
    commit = subprocess.run(["git", "rev-parse", "--short", "HEAD"], cwd=ROOT, capture_output=True,
                            text=True).stdout.strip()
    baseline = ""
    if args.baseline:
        baseline = subprocess.run(["git", "rev-parse", "--short", "HEAD"], cwd=args.baseline, capture_output=True,
                                  text=True).stdout.strip()
    record = {"command": "python benchmarks/replay_placement.py " + shlex.join(sys.argv[1:]), "commit": commit,
              "baseline_commit": baseline, "date": time.strftime("%Y-%m-%d"),
              "machine": f"{platform.machine()}, {len(os.sched_getaffinity(0))} usable cores",
              "iterations": args.iterations, "medians": summary, "runs": runs}
    args.json.parent.mkdir(parents=True, exist_ok=True)
    args.json.write_text(json.dumps(record, indent=1) + "\n")
    print(json.dumps(summary, indent=1))


if __name__ == "__main__":
    main()
