"""Learning speed: return vs wall clock for ebrl and colocated at the same env-step budget.

    python benchmarks/learning_speed.py --config configs/quickstart.toml --iterations 150

Both modes train the same config for the same number of updates; one update
consumes ``train.batch_size`` decisions of ``policy.chunk`` env steps in both,
so the env-step budget is the same. Modes run one after the other on the same
machine. Writes benchmarks/results/learning_speed.{json,png}: the curves, the
final values (mean of the last 5 reports), the best return, and the wall time
each mode took to use the budget.
"""

from __future__ import annotations

import argparse
import json
import statistics
import sys
from pathlib import Path

sys.path.insert(0, str(Path(__file__).resolve().parent.parent))

from ebrl import bench, config  # noqa: E402

RESULTS = Path(__file__).resolve().parent / "results"


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    parser.add_argument("--config", default="configs/quickstart.toml")
    parser.add_argument("--modes", default="ebrl,colocated")
    parser.add_argument("--iterations", type=int, default=150)
    parser.add_argument("--out", default=str(RESULTS), help="directory for learning_speed.{json,png}")
    args = parser.parse_args()
    out = Path(args.out)
    out.mkdir(parents=True, exist_ok=True)
    cfg = config.load(args.config)
    budget = args.iterations * cfg.train.batch_size * cfg.policy.chunk
    curves, summary = {}, {}
    for mode in args.modes.split(","):
        print(f"{mode}: {args.iterations} updates ({budget:,} env steps) ...", file=sys.stderr, flush=True)
        curve = bench.learning_curve(args.config, [f"run.mode={mode}", f"run.iterations={args.iterations}",
                                                   "run.target_return=1e9"], name=f"learning-{mode}")
        curves[mode] = curve
        summary[mode] = {"final_return_last5": statistics.fmean(p["return"] for p in curve[-5:]),
                         "best_return": max(p["return"] for p in curve), "wall_s": curve[-1]["wall_s"],
                         "env_steps": curve[-1]["env_steps"]}
    plot(curves, args, budget, out / "learning_speed.png")
    result = {"command": "python benchmarks/learning_speed.py " + " ".join(sys.argv[1:]), "config": args.config,
              "iterations": args.iterations, "env_step_budget": budget, "summary": summary, "curves": curves}
    (out / "learning_speed.json").write_text(json.dumps(result, indent=2) + "\n")
    print(json.dumps(summary, indent=2))


def plot(curves: dict, args, budget: int, path: Path) -> None:
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    fig, ax = plt.subplots(figsize=(7, 4))
    for mode, curve in curves.items():
        ax.plot([p["wall_s"] for p in curve], [p["return"] for p in curve], label=mode)
    ax.set_xlabel("wall-clock seconds since launch")
    ax.set_ylabel("mean return (last 20 episodes)")
    ax.set_title(f"{Path(args.config).stem}: {args.iterations} updates, {budget:,} env steps each")
    ax.legend()
    fig.tight_layout()
    fig.savefig(path, dpi=100)


if __name__ == "__main__":
    main()
