"""Bounded staleness: throughput at several max_staleness values, and learning at 1 vs 8.

    python benchmarks/staleness.py throughput --duration 60          # W1 (robosuite Lift), ebrl mode
    python benchmarks/staleness.py learning --iterations 200         # quickstart, return vs wall clock

Results go to benchmarks/results/staleness_*.json (and a PNG of the learning curves).
"""

from __future__ import annotations

import argparse
import json
import statistics
import sys
from pathlib import Path

sys.path.insert(0, str(Path(__file__).resolve().parent.parent))

from ebrl import bench  # noqa: E402

RESULTS = Path(__file__).resolve().parent / "results"


def throughput(args) -> None:
    values = [int(v) for v in args.staleness.split(",")]
    runs: dict[int, list[dict]] = {s: [] for s in values}
    for r in range(args.repeat):
        for s in values:  # interleaved
            print(f"[{r + 1}/{args.repeat}] max_staleness={s}", file=sys.stderr, flush=True)
            runs[s].append(bench.measure(args.config, "ebrl", [f"algo.max_staleness={s}"], args.duration))
    med = {s: statistics.median(x["traj_per_s"] for x in runs[s]) for s in values}
    steps = {s: statistics.median(x["env_steps_per_s"] for x in runs[s]) for s in values}
    spread = (max(steps.values()) - min(steps.values())) / max(steps.values())
    result = {"command": "python benchmarks/staleness.py throughput " + " ".join(sys.argv[2:]),
              "config": args.config, "duration_s": args.duration, "repeat": args.repeat,
              "traj_per_s_median": med, "env_steps_per_s_median": steps, "runs": runs,
              "env_steps_spread_ratio": spread}
    (RESULTS / "staleness_throughput.json").write_text(json.dumps(result, indent=2) + "\n")
    line = ", ".join(f"S={s}: {steps[s]:.0f} steps/s" for s in values)
    print(f"throughput vs max_staleness ({args.config}): {line}; spread {spread * 100:.1f}%")


def learning(args) -> None:
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    values = [int(v) for v in args.staleness.split(",")]
    curves = {}
    for s in values:
        print(f"learning with max_staleness={s}", file=sys.stderr, flush=True)
        curves[s] = bench.learning_curve(args.config, [f"algo.max_staleness={s}", f"run.iterations={args.iterations}",
                                                       "run.target_return=1e9"], name=f"staleness-{s}")
    finals = {s: statistics.fmean(p["return"] for p in c[-5:]) for s, c in curves.items()}
    best = {s: max(p["return"] for p in c) for s, c in curves.items()}
    fig, ax = plt.subplots(figsize=(7, 4))
    for s, c in curves.items():
        ax.plot([p["wall_s"] for p in c], [p["return"] for p in c], label=f"max_staleness={s}")
    ax.set_xlabel("wall-clock seconds since launch")
    ax.set_ylabel("mean return (last 20 episodes)")
    ax.set_title(f"{Path(args.config).stem}: {args.iterations} updates")
    ax.legend()
    fig.tight_layout()
    fig.savefig(RESULTS / "staleness_learning.png", dpi=100)
    result = {"command": "python benchmarks/staleness.py learning " + " ".join(sys.argv[2:]),
              "config": args.config, "iterations": args.iterations, "final_return_last5": finals,
              "best_return": best, "curves": curves}
    (RESULTS / "staleness_learning.json").write_text(json.dumps(result, indent=2) + "\n")
    line = ", ".join(f"S={s}: final {finals[s]:.0f} (best {best[s]:.0f})" for s in values)
    print(f"learning vs max_staleness ({args.config}, {args.iterations} updates): {line}")


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    sub = parser.add_subparsers(dest="what", required=True)
    p = sub.add_parser("throughput")
    p.add_argument("--config", default="configs/robosuite_lift.toml")
    p.add_argument("--staleness", default="1,2,4,8")
    p.add_argument("--duration", type=float, default=60.0)
    p.add_argument("--repeat", type=int, default=1)
    p.set_defaults(run=throughput)
    p = sub.add_parser("learning")
    p.add_argument("--config", default="configs/quickstart.toml")
    p.add_argument("--staleness", default="1,8")
    p.add_argument("--iterations", type=int, default=200)
    p.set_defaults(run=learning)
    args = parser.parse_args()
    RESULTS.mkdir(parents=True, exist_ok=True)
    args.run(args)


if __name__ == "__main__":
    main()
