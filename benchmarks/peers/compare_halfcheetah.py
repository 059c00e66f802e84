"""HalfCheetah: wall-clock time to a stated return for EBRL and two outside peers, run one after the other.

    python benchmarks/peers/compare_halfcheetah.py --target-return 1000 --max-seconds 900

Runs, in this order and never two at once, each until the mean return of the
last 20 episodes reaches ``--target-return`` or ``--max-seconds`` pass (wall
clock from launch):

* EBRL: ``ebrl up configs/bench_halfcheetah.toml`` with ``run.target_return`` set;
* EBRL again with ``policy.normalize_obs = true`` (running observation statistics, as the peers use);
* the CleanRL-style loop: ``cleanrl_ppo.py --env HalfCheetah-v5 --num-envs 8``;
* Sample Factory 2: ``sample_factory.py`` (its MuJoCo example, synchronous, its default),
  and again with ``--async_rl=True`` (``--runs`` picks a subset).

Each peer keeps its own settings and writes its own JSON under
benchmarks/results/; this script collects the summaries, EBRL's curve and the
speed-up of each EBRL run over the fastest peer into ``peer_comparison_halfcheetah.json``. When
that file exists, runs not selected with ``--runs`` keep their recorded results, so one system can be
measured again on its own.
"""

from __future__ import annotations

import argparse
import json
import shlex
import subprocess
import sys
import time
from pathlib import Path

HERE = Path(__file__).resolve().parent
ROOT = HERE.parent.parent
sys.path.insert(0, str(ROOT))

from ebrl import bench  # noqa: E402

RESULTS = ROOT / "benchmarks" / "results"
RUNS = "runs/peers"


def run_ebrl(args: argparse.Namespace, name: str, extra: list[str]) -> dict:
    overrides = [f"run.target_return={args.target_return}", *extra]
    if args.ebrl_seed is not None:
        overrides.append(f"run.seed={args.ebrl_seed}")
    curve = bench.learning_curve(args.config, overrides, name, timeout=args.max_seconds, out_dir=RUNS)
    run_dir = max((ROOT / RUNS).glob(f"{name}-*"), key=lambda p: p.stat().st_mtime)
    summary = json.loads((run_dir / "summary.json").read_text())
    return {"command": shlex.join(["ebrl", "up", args.config, *[a for o in overrides for a in ("--set", o)]]),
            "summary": summary, "curve": curve}


def run_peer(script: str, extra: list[str], out: Path, args: argparse.Namespace) -> dict:
    cmd = [sys.executable, str(HERE / script), "--target-return", str(args.target_return),
           "--max-seconds", str(args.max_seconds), "--seed", str(args.seed), "--json", str(out), *extra]
    print("$ " + shlex.join(cmd), flush=True)
    subprocess.run(cmd, check=True, cwd=ROOT)
    result = json.loads(out.read_text())
    return {"command": result["command"], "json": str(out.relative_to(ROOT)), "summary": result["summary"]}


EBRL = {
    "ebrl": lambda a: run_ebrl(a, "peer-halfcheetah", []),
    "ebrl_obs_norm": lambda a: run_ebrl(a, "peer-halfcheetah-obs-norm", ["policy.normalize_obs=true"]),
}
PEERS = {
    "cleanrl_ppo": lambda a: run_peer("cleanrl_ppo.py", ["--env", "HalfCheetah-v5", "--num-envs", "8"],
                                      RESULTS / "peer_cleanrl_ppo_halfcheetah.json", a),
    "sample_factory": lambda a: run_peer("sample_factory.py", [], RESULTS / "peer_sample_factory.json", a),
    "sample_factory_async": lambda a: run_peer("sample_factory.py", ["--async_rl=True"],
                                               RESULTS / "peer_sample_factory_async.json", a),
}


def time_to_target(summary: dict) -> float | None:
    reached = summary.get("target_reached")
    return None if reached is None else reached["wall_s"]


def write(args: argparse.Namespace, results: dict[str, dict]) -> dict:
    """Write the comparison so far; return its headline numbers."""
    times = {run: time_to_target(r["summary"]) for run, r in results.items()}
    peers = {run: t for run, t in times.items() if run in PEERS and t is not None}
    fastest = min(peers, key=peers.get, default=None)
    headline = {
        "time_to_target_s": times,
        "fastest_peer": fastest,
        "speedup_over_fastest_peer": {run: round(peers[fastest] / t, 2) for run, t in times.items()
                                      if run in EBRL and t is not None and fastest is not None},
    }
    out = {"command": "python benchmarks/peers/compare_halfcheetah.py " + shlex.join(sys.argv[1:]),
           "date": time.strftime("%Y-%m-%d"), "target_return": args.target_return,
           "max_seconds": args.max_seconds, **headline, **results}
    Path(args.json).write_text(json.dumps(out, indent=2) + "\n")
    return headline


def main() -> int:
    p = argparse.ArgumentParser(description=__doc__.split("\n")[0],
                                formatter_class=argparse.ArgumentDefaultsHelpFormatter)
    p.add_argument("--config", default="configs/bench_halfcheetah.toml")
    p.add_argument("--target-return", type=float, default=1000.0)
    p.add_argument("--max-seconds", type=float, default=900.0, help="wall-clock cap of each run")
    p.add_argument("--seed", type=int, default=0, help="seed of the peers")
    p.add_argument("--ebrl-seed", type=int, default=None, help="EBRL's run.seed (default: the config's)")
    p.add_argument("--runs", default=",".join([*EBRL, *PEERS]), help="which runs, in this order")
    p.add_argument("--json", default=str(RESULTS / "peer_comparison_halfcheetah.json"))
    args = p.parse_args()

    results: dict[str, dict] = {}
    recorded = Path(args.json)
    if recorded.exists():  # keep the runs not measured now
        earlier = json.loads(recorded.read_text())
        if earlier.get("target_return") == args.target_return:
            results = {run: earlier[run] for run in {**EBRL, **PEERS} if run in earlier}
    for run in args.runs.split(","):
        print(f"== {run}", flush=True)
        results[run] = {**EBRL, **PEERS}[run](args)
        summary = write(args, results)  # after every run: a later failure keeps the earlier results
    print(json.dumps(summary, indent=2))
    print(f"wrote {args.json}")
    return 0


if __name__ == "__main__":
    sys.exit(main())
