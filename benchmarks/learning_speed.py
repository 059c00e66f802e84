"""Learning speed: return vs wall clock for ebrl and colocated at the same env-step budget.

    python benchmarks/learning_speed.py --config configs/quickstart.toml --iterations 150 [--seeds 0,1,2]

Both modes train the same config for the same number of updates; one update
consumes ``train.batch_size`` decisions of ``policy.chunk`` env steps in both,
so the env-step budget is the same. Runs go one after the other on the same
machine, the modes interleaved seed by seed; ``--set`` overrides the config of
every run. Writes benchmarks/results/NAME.{json,png} (``--name``, default
learning_speed): the curves, the final values
(mean of the last 5 reports), the best return, and the wall time each mode took
to use the budget -- per seed (``per_seed``) and, in ``summary``, their median;
``curves`` holds the first seed's curves, ``curves_by_seed`` all of them.
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
    parser.add_argument("--seeds", default="", help="comma-separated run.seed values (default: the config's)")
    parser.add_argument("--set", action="append", default=[], dest="overrides", metavar="SECTION.KEY=VALUE",
                        help="a config override for every run (e.g. train.overlap=false)")
    parser.add_argument("--out", default=str(RESULTS), help="directory for NAME.{json,png}")
    parser.add_argument("--name", default="learning_speed", help="file name of the results (without extension)")
    args = parser.parse_args()
    out = Path(args.out)
    out.mkdir(parents=True, exist_ok=True)
    cfg = config.load(args.config, args.overrides)
    budget = args.iterations * cfg.train.batch_size * cfg.policy.chunk
    seeds = [int(s) for s in args.seeds.split(",") if s.strip()] or [cfg.run.seed]
    modes = args.modes.split(",")
    by_seed: dict[str, dict[str, list]] = {mode: {} for mode in modes}
    per_seed: dict[str, dict[str, dict]] = {mode: {} for mode in modes}
    for seed in seeds:
        for mode in modes:
            print(f"{mode}, seed {seed}: {args.iterations} updates ({budget:,} env steps) ...", file=sys.stderr,
                  flush=True)
            curve = bench.learning_curve(args.config, [*args.overrides, f"run.mode={mode}",
                                                       f"run.iterations={args.iterations}", "run.target_return=1e9",
                                                       f"run.seed={seed}"], name=f"learning-{mode}")
            by_seed[mode][str(seed)] = curve
            per_seed[mode][str(seed)] = {"final_return_last5": statistics.fmean(p["return"] for p in curve[-5:]),
                                         "best_return": max(p["return"] for p in curve),
                                         "wall_s": curve[-1]["wall_s"], "env_steps": curve[-1]["env_steps"]}
    summary = {mode: {key: statistics.median(run[key] for run in per_seed[mode].values())
                      for key in ("final_return_last5", "best_return", "wall_s", "env_steps")} for mode in modes}
    curves = {mode: by_seed[mode][str(seeds[0])] for mode in modes}
    plot(by_seed, args, budget, out / f"{args.name}.png")
    result = {"command": "python benchmarks/learning_speed.py " + " ".join(sys.argv[1:]), "config": args.config,
              "iterations": args.iterations, "env_step_budget": budget, "seeds": seeds, "overrides": args.overrides,
              "summary": summary,
              "per_seed": per_seed, "curves": curves, "curves_by_seed": by_seed}
    (out / f"{args.name}.json").write_text(json.dumps(result, indent=2) + "\n")
    print(json.dumps(summary, indent=2))


def plot(by_seed: dict[str, dict[str, list]], args, budget: int, path: Path) -> None:
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    fig, ax = plt.subplots(figsize=(7, 4))
    for color, (mode, curves) in zip(("tab:blue", "tab:orange", "tab:green", "tab:red"), by_seed.items()):
        for i, (seed, curve) in enumerate(curves.items()):
            ax.plot([p["wall_s"] for p in curve], [p["return"] for p in curve], color=color, alpha=0.8,
                    label=mode if i == 0 else None, linewidth=1.2)
    ax.set_xlabel("wall-clock seconds since launch")
    ax.set_ylabel("mean return (last 20 episodes)")
    ax.set_title(f"{Path(args.config).stem}: {args.iterations} updates, {budget:,} env steps each")
    ax.legend()
    fig.tight_layout()
    fig.savefig(path, dpi=100)


if __name__ == "__main__":
    main()
