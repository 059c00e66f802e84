"""Data-parallel training: learning curves with train.world_size = 1 and 2 on the same config and seeds.

    python benchmarks/data_parallel.py --config configs/quickstart.toml --world-sizes 1,2 --seeds 0,1 --iterations 150

Two ranks split each update's batch and all-reduce their gradients (ebrl.algos.parallel), so per update they
should learn what one rank learns; this checks it on the real run. Every (world size, seed) trains for the same
number of updates with run.target_return out of reach, interleaved (seed 0: W = 1, 2; seed 1: W = 1, 2; ...)
so that drift of a shared machine hits both world sizes alike. The curve is the mean return of the last 20
episodes at each sim stats report, against the update (policy version) and env steps. Per world size it reports
the first update whose report reached --threshold (the quickstart's 900) and the final return (mean of the last
5 reports), per seed and averaged. Writes benchmarks/results/data_parallel_learning.{json,png}.
"""

from __future__ import annotations

import argparse
import json
import os
import statistics
import sys
from pathlib import Path

sys.path.insert(0, str(Path(__file__).resolve().parent.parent))

from ebrl import bench, config  # noqa: E402

RESULTS = Path(__file__).resolve().parent / "results"


def first_reaching(curve: list[dict[str, float]], threshold: float) -> int | None:
    """The policy version of the first report at or above ``threshold`` (None: never)."""
    return next((int(p["policy_version"]) for p in curve if p["return"] >= threshold), None)


def summarize(runs: dict[int, dict[int, list[dict[str, float]]]], threshold: float) -> dict[int, dict]:
    out = {}
    for world, by_seed in runs.items():
        seeds = {seed: {"first_iteration_at_threshold": first_reaching(curve, threshold),
                        "final_return_last5": statistics.fmean(p["return"] for p in curve[-5:]),
                        "best_return": max(p["return"] for p in curve), "wall_s": curve[-1]["wall_s"],
                        "env_steps": curve[-1]["env_steps"]} for seed, curve in by_seed.items()}
        reached = [s["first_iteration_at_threshold"] for s in seeds.values()]
        out[world] = {
            "per_seed": seeds,
            "seeds_reaching_threshold": sum(r is not None for r in reached),
            "first_iteration_at_threshold_mean": statistics.fmean(reached) if None not in reached else None,
            "final_return_last5_mean": statistics.fmean(s["final_return_last5"] for s in seeds.values()),
            "wall_s_mean": statistics.fmean(s["wall_s"] for s in seeds.values()),
        }
    return out


def table(summary: dict[int, dict], threshold: float) -> str:
    head = ("W ranks", "seed", f"first update >= {threshold:g}", "final return (last 5)", "best", "wall s")
    rows = [head]
    for world, s in summary.items():
        for seed, r in s["per_seed"].items():
            first = r["first_iteration_at_threshold"]
            rows.append((str(world), str(seed), "never" if first is None else str(first),
                         f"{r['final_return_last5']:.1f}", f"{r['best_return']:.1f}", f"{r['wall_s']:.0f}"))
        mean_first = s["first_iteration_at_threshold_mean"]
        rows.append((str(world), "mean", "-" if mean_first is None else f"{mean_first:.0f}",
                     f"{s['final_return_last5_mean']:.1f}", "", f"{s['wall_s_mean']:.0f}"))
    widths = [max(len(r[i]) for r in rows) for i in range(len(head))]
    return "\n".join("  ".join(c.ljust(w) for c, w in zip(r, widths)) for r in rows)


def plot(runs: dict[int, dict[int, list[dict[str, float]]]], args, path: Path) -> None:
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    fig, (by_update, by_wall) = plt.subplots(1, 2, figsize=(11, 4), sharey=True)
    styles = ["-", "--", ":", "-."]
    for i, (world, by_seed) in enumerate(runs.items()):
        for j, (seed, curve) in enumerate(by_seed.items()):
            kw = dict(color=f"C{i}", linestyle=styles[j % len(styles)], label=f"world_size {world}, seed {seed}")
            by_update.plot([p["policy_version"] for p in curve], [p["return"] for p in curve], **kw)
            by_wall.plot([p["wall_s"] for p in curve], [p["return"] for p in curve], **kw)
    for ax in (by_update, by_wall):
        ax.axhline(args.threshold, color="grey", linewidth=0.8)
    by_update.set_xlabel("update (policy version)")
    by_wall.set_xlabel("wall-clock seconds since launch")
    by_update.set_ylabel("mean return (last 20 episodes)")
    by_update.legend(fontsize=8)
    fig.suptitle(f"{Path(args.config).stem}: train.world_size 1 vs 2, {args.iterations} updates")
    fig.tight_layout()
    fig.savefig(path, dpi=100)


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    parser.add_argument("--config", default="configs/quickstart.toml")
    parser.add_argument("--world-sizes", default="1,2")
    parser.add_argument("--seeds", default="0,1")
    parser.add_argument("--iterations", type=int, default=150)
    parser.add_argument("--threshold", type=float, default=900.0, help="return whose first update is reported")
    parser.add_argument("--out", default=str(RESULTS), help="directory for data_parallel_learning.{json,png}")
    args = parser.parse_args()
    out = Path(args.out)
    out.mkdir(parents=True, exist_ok=True)
    worlds = [int(w) for w in args.world_sizes.split(",")]
    seeds = [int(s) for s in args.seeds.split(",")]
    cfg = config.load(args.config)
    budget = args.iterations * cfg.train.batch_size * cfg.policy.chunk
    runs: dict[int, dict[int, list]] = {w: {} for w in worlds}
    load_before = os.getloadavg()
    for seed in seeds:
        for world in worlds:
            print(f"world_size {world}, seed {seed}: {args.iterations} updates ({budget:,} env steps) ...",
                  file=sys.stderr, flush=True)
            runs[world][seed] = bench.learning_curve(
                args.config, [f"train.world_size={world}", f"run.seed={seed}", f"run.iterations={args.iterations}",
                              "run.target_return=1e9", 'viz.rerun="off"'], name=f"dp-w{world}-s{seed}")
    summary = summarize(runs, args.threshold)
    print(table(summary, args.threshold))
    plot(runs, args, out / "data_parallel_learning.png")
    (out / "data_parallel_learning.json").write_text(json.dumps({
        "command": " ".join(["python benchmarks/data_parallel.py", *sys.argv[1:]]), "config": args.config,
        "machine": {"usable_cores": len(os.sched_getaffinity(0)), "load_average_before": load_before,
                    "load_average_after": os.getloadavg()},
        "iterations": args.iterations, "env_step_budget": budget, "threshold": args.threshold, "seeds": seeds,
        "summary": summary, "curves": runs}, indent=2) + "\n")


if __name__ == "__main__":
    main()
