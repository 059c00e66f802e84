"""Updates, env steps and seconds to 90 % success on PandaPickCube: EBRL against the one-process peer, seed by seed.

    python benchmarks/pickcube_race.py --seeds 0,1,2,3                    # Warp's CPU device, 2 x 64 worlds
    python benchmarks/pickcube_race.py --seeds 0,1,2 --gpu                # the GPU race at its own size

Each seed runs ``ebrl up configs/mjwarp_pickcube.toml`` (``run.seed`` set; ``--mode`` for another mode) and
``benchmarks/peers/mjwarp_ppo.py --seed S`` on the same MuJoCo Warp batch of ``PandaPickCube-v0``; both stop at
90 % success over the last 20 episodes, or at ``--max-seconds``. Without ``--gpu`` the two sides run at the
GPU race's proportions on Warp's CPU device, small enough for 2 cores: one env step per decision
(``policy.chunk = 1``), 128 worlds (EBRL: 2 groups of 64), 32 steps of each world per update (EBRL: 4096
decisions, segments of 32), the config's network and PPO settings on both sides.

How many updates a seed needs varies about 2x from seed to seed on either side, so one pair says little;
the medians over the seeds are the comparison. ``--jobs`` runs that many at once: the peer's updates and env
steps to the target do not depend on it, EBRL's do a little (how stale its data is depends on timing), and
seconds compare only between runs made one at a time (the default). Writes ``--json`` (default
``benchmarks/results/pickcube_race_cpu.json``): each run's command, whether and when it reached the target
(updates, env steps, seconds), and per side the medians.
"""

from __future__ import annotations

import argparse
import concurrent.futures
import json
import os
import platform
import shlex
import signal
import statistics
import subprocess
import sys
import tempfile
import time
from pathlib import Path

ROOT = Path(__file__).resolve().parent.parent
sys.path.insert(0, str(ROOT))

from ebrl import bench  # noqa: E402

CONFIG = "configs/mjwarp_pickcube.toml"
# the GPU race's proportions on Warp's CPU device: 128 worlds, one step per decision, 32 of each world an update
CPU_SETS = ["sim.envs_per_group=64", "policy.chunk=1", "train.batch_size=4096", "train.max_pending=8192",
            "sim.segment_length=32"]
CPU_PEER = ["--device", "cpu", "--num-envs", "128"]


def ebrl_command(seed: int, mode: str, gpu: bool, out: Path, extra: list[str]) -> list[str]:
    sets = ([] if gpu else CPU_SETS) + [f"run.seed={seed}", f'run.mode="{mode}"', 'viz.rerun="off"', *extra]
    argv = ["ebrl", "up", CONFIG]
    for item in sets:
        argv += ["--set", item]
    return argv + ["--set", f'run.output_dir="{out}"']


def peer_command(seed: int, gpu: bool, max_seconds: float, out: Path) -> list[str]:
    return ["python", "benchmarks/peers/mjwarp_ppo.py", *([] if gpu else CPU_PEER), "--seed", str(seed),
            "--max-seconds", f"{max_seconds:g}", "--json", str(out)]


def shown(argv: list[str], drop_from: str) -> str:
    """The command as a user types it, without the scratch output path (``drop_from`` onwards)."""
    cut = argv.index(drop_from) if drop_from in argv else len(argv)
    if argv[:2] == ["ebrl", "up"] and cut >= 2 and argv[cut - 1] == "--set":
        cut -= 1
    return shlex.join(argv[:cut])


def run_ebrl(seed: int, args: argparse.Namespace, scratch: Path) -> dict:
    out = scratch / f"ebrl-{seed}"
    argv = ebrl_command(seed, args.mode, args.gpu, out, args.set)
    started = time.monotonic()
    proc = subprocess.Popen([sys.executable, "-m", "ebrl.cli", *argv[1:]], cwd=ROOT, stdout=subprocess.DEVNULL,
                            stderr=subprocess.DEVNULL)
    try:
        proc.wait(timeout=args.max_seconds)
    except subprocess.TimeoutExpired:  # out of time: Ctrl-C, as a user would (the run writes its summary)
        proc.send_signal(signal.SIGINT)
        try:
            proc.wait(timeout=120)
        except subprocess.TimeoutExpired:  # it did not stop: no summary, the row says so
            proc.kill()
            proc.wait()
    summaries = sorted(out.glob("*/summary.json"))
    summary = json.loads(summaries[-1].read_text()) if summaries else {}
    reached = summary.get("target_reached")
    return {"side": f"ebrl ({args.mode})", "seed": seed, "command": shown(argv, f'run.output_dir="{out}"'),
            "exit_code": proc.returncode, "wall_s": round(time.monotonic() - started, 1),
            "reached": reached is not None, "updates": reached and reached["iteration"],
            "seconds": reached and reached["wall_s"], "env_steps_total": summary.get("env_steps"),
            "updates_total": summary.get("iterations")}


def run_peer(seed: int, args: argparse.Namespace, scratch: Path) -> dict:
    out = scratch / f"peer-{seed}.json"
    argv = peer_command(seed, args.gpu, args.max_seconds, out)
    started = time.monotonic()
    proc = subprocess.run([sys.executable, *argv[1:]], cwd=ROOT, stdout=subprocess.DEVNULL, stderr=subprocess.DEVNULL,
                          timeout=args.max_seconds + 120)
    summary = json.loads(out.read_text())["summary"] if out.exists() else {}
    reached = summary.get("target_reached")
    return {"side": "peer", "seed": seed, "command": shown(argv, "--json"), "exit_code": proc.returncode,
            "wall_s": round(time.monotonic() - started, 1), "reached": reached is not None,
            "updates": reached and reached["updates"], "env_steps": reached and reached["env_steps"],
            "seconds": reached and reached["wall_s"], "env_steps_total": summary.get("env_steps"),
            "updates_total": summary.get("updates")}


def medians(runs: list[dict]) -> dict:
    """Per side: seeds that reached the target, and the medians over all seeds (one that did not reach it counts
    as its whole run: a lower bound, so a median that includes one says "at least")."""
    out = {}
    for side in sorted({r["side"] for r in runs}):
        rows = [r for r in runs if r["side"] == side]
        out[side] = {"seeds": len(rows), "reached": sum(r["reached"] for r in rows),
                     "median_updates": statistics.median(r["updates"] if r["reached"] else r["updates_total"] or 0
                                                         for r in rows),
                     "median_seconds": statistics.median(r["seconds"] if r["reached"] else r["wall_s"]
                                                         for r in rows)}
    return out


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    parser.add_argument("--seeds", default="0,1,2,3")
    parser.add_argument("--sides", default="ebrl,peer", help="ebrl, peer or both")
    parser.add_argument("--mode", default="ebrl", help="EBRL's run.mode (ebrl, colocated, ...)")
    parser.add_argument("--gpu", action="store_true", help="the config's own size on the GPU, not the CPU proportions")
    parser.add_argument("--max-seconds", type=float, default=1800.0, help="each run stops here at the latest")
    parser.add_argument("--jobs", type=int, default=1, help="runs at once")
    parser.add_argument("--set", action="append", default=[], metavar="SECTION.KEY=VALUE", help="for EBRL's runs")
    parser.add_argument("--json", default=str(ROOT / "benchmarks/results/pickcube_race_cpu.json"))
    args = parser.parse_args()
    seeds = [int(s) for s in args.seeds.split(",") if s.strip()]
    sides = [s.strip() for s in args.sides.replace("both", "ebrl,peer").split(",") if s.strip()]
    if unknown := set(sides) - {"ebrl", "peer"}:
        parser.error(f"--sides: {', '.join(sorted(unknown))} is not a side (ebrl, peer or both)")
    jobs = [(side, seed) for seed in seeds for side in sides]
    with tempfile.TemporaryDirectory(prefix="pickcube-race-") as scratch, \
            concurrent.futures.ThreadPoolExecutor(max(1, args.jobs)) as pool:
        futures = [pool.submit(run_ebrl if side == "ebrl" else run_peer, seed, args, Path(scratch))
                   for side, seed in jobs]
        runs = []
        for future in futures:
            runs.append(row := future.result())
            print(f"{row['side']:18s} seed {row['seed']}: " + (
                f"90 % after {row['updates']} updates, {row['seconds']:.0f} s" if row["reached"] else
                f"not reached ({row['updates_total']} updates, exit {row['exit_code']})"), flush=True)
    machine = f"{platform.machine()}, {len(os.sched_getaffinity(0))} usable cores"
    result = {"command": "python benchmarks/pickcube_race.py " + " ".join(sys.argv[1:]), "commit": bench.commit(),
              "date": time.strftime("%Y-%m-%d"), "machine": machine,
              "jobs": args.jobs, "runs": runs, "medians": medians(runs)}
    Path(args.json).write_text(json.dumps(result, indent=2) + "\n")
    for side, m in result["medians"].items():
        print(f"{side}: {m['reached']}/{m['seeds']} seeds reached 90 %; median {m['median_updates']} updates, "
              f"{m['median_seconds']:.0f} s")


if __name__ == "__main__":
    main()
