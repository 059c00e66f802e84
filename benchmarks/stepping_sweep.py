"""Stepping sweep: the ebrl mode with its defaults against the best baseline, over step-latency workloads.

Each point is one ``ebrl bench`` comparison (``ebrl.bench.run``: real ``ebrl up`` runs, modes interleaved,
throughput read from the stats stream): ``ebrl`` (defaults: ``sim.core_rebinding = "auto"``) against
``colocated``, ``hybrid`` and ``async``. Points:

* ``lat:<mean_ms>:<sigma>`` — ``configs/bench_stepping.toml`` (the robosuite Lift config's settings on a cheap
  simulator) with the ``env.latency`` wrapper: lognormal CPU-bound step latency of that mean and sigma;
* ``halfcheetah`` — ``configs/bench_halfcheetah.toml`` (HalfCheetah-v5, ~75 µs steps);
* ``lift`` — ``configs/robosuite_lift.toml`` (robosuite Lift, ~16 ms steps).

Each ``lat`` point also records what the cores allow (:func:`ceiling`): its steps cost their mean latency in CPU
time, so ``cores * 1000 / mean_ms`` env steps/s bounds every mode, and that ceiling over the best baseline's
rate is the highest ratio any scheduler could read there.

Results are merged into the JSON file point by point (a point already there is skipped unless ``--force``; a
point measured again keeps the earlier verdicts under ``earlier``), so the sweep can run one command per point,
across sessions, and a plot of every point so far is redrawn:

    python benchmarks/stepping_sweep.py                       # every point (about 3 minutes each)
    python benchmarks/stepping_sweep.py --points lat:2:1.0    # one point
    python benchmarks/stepping_sweep.py --plot-only
"""

from __future__ import annotations

import argparse
import json
import os
import platform
import statistics
import sys
import time
from pathlib import Path

sys.path.insert(0, str(Path(__file__).resolve().parent.parent))

from ebrl import bench  # noqa: E402

ROOT = Path(__file__).resolve().parent.parent
MEANS = (0.2, 0.5, 1.0, 2.0, 4.0, 8.0, 16.0, 32.0)
SIGMAS = (0.3, 1.0)
NAMED = {"halfcheetah": "configs/bench_halfcheetah.toml", "lift": "configs/robosuite_lift.toml"}
MODES = ("ebrl", *bench.BASELINES)
# what a point measured again keeps of its earlier measurement (under "earlier", oldest first)
EARLIER_KEYS = ("command", "commit", "duration_s", "repeat", "ebrl_vs_best", "ebrl_vs_best_env_steps", "best_baseline")


def all_points() -> list[str]:
    return [f"lat:{m:g}:{s:g}" for s in SIGMAS for m in MEANS] + list(NAMED)


def point_config(point: str) -> tuple[str, list[str]]:
    """The config and overrides of a point name."""
    if point in NAMED:
        return NAMED[point], []
    kind, mean, sigma = point.split(":")
    if kind != "lat":
        raise ValueError(f"unknown point {point!r}: lat:<mean_ms>:<sigma>, {', '.join(NAMED)}")
    return "configs/bench_stepping.toml", [f"env.latency_mean_ms={float(mean)}", f"env.latency_sigma={float(sigma)}"]


def ceiling(point: str, cores: int, summary: dict) -> dict:
    """What the cores allow at a ``lat`` point: its steps cost ``mean_ms`` of CPU each (the wrapper busy-waits on
    the thread's CPU clock), so no mode completes more than ``cores * 1000 / mean_ms`` env steps/s -- fewer, as
    generation, training and the services need the same cores. Returns that ceiling, ebrl's and the best
    baseline's share of it, and the highest ratio over the best baseline any mode could read
    (``ceiling_vs_best``); {} for the named points, whose step cost is not set."""
    if not point.startswith("lat:"):
        return {}
    top = cores * 1e3 / float(point.split(":")[1])
    steps = {m: statistics.median(r["env_steps_per_s"] for r in runs) for m, runs in summary["results"].items()}
    best = max(steps[m] for m in bench.BASELINES)
    return {"cores": cores, "env_steps_ceiling": top, "ebrl_of_ceiling": steps["ebrl"] / top,
            "best_of_ceiling": best / top, "ceiling_vs_best": top / best}


def machine_cores(machine: str) -> int:
    """The usable cores a point was measured on, from its ``machine`` text ("x86_64, 2 usable cores")."""
    return int(machine.split(",")[1].split()[0])


def summarize_point(results: dict[str, list[dict]]) -> dict:
    med = {m: statistics.median(r["traj_per_s"] for r in runs) for m, runs in results.items()}
    best = max(bench.BASELINES, key=lambda m: med.get(m, 0.0))
    steps = {m: statistics.median(r["env_steps_per_s"] for r in runs) for m, runs in results.items()}
    return {"traj_per_s": med, "best_baseline": best, "ebrl_vs_best": med["ebrl"] / med[best],
            "ebrl_vs_best_env_steps": steps["ebrl"] / max(steps[m] for m in bench.BASELINES),
            "ebrl_rebinding_share": [r.get("rebinding_share") for r in results["ebrl"]],
            "ebrl_rebinding_gain": [r.get("rebinding_gain") for r in results["ebrl"]]}


def measure_point(point: str, duration: float, repeat: int, extra: list[str]) -> dict:
    config, overrides = point_config(point)
    variants = {m: [*overrides, *extra] for m in MODES}
    started = time.time()
    results = bench.run(str(ROOT / config), variants, duration, repeat, raw_seconds=0)
    return {"config": config, "overrides": overrides + extra, "duration_s": duration, "repeat": repeat,
            "seconds": time.time() - started, "results": results, **summarize_point(results)}


def plot(data: dict, path: Path) -> None:
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    fig, ax = plt.subplots(figsize=(7, 4))
    for sigma in SIGMAS:
        xs = [(m, p) for m in MEANS if (p := data["points"].get(f"lat:{m:g}:{sigma:g}"))]
        if xs:
            ax.plot([m for m, _ in xs], [p["ebrl_vs_best"] for _, p in xs], marker="o",
                    label=f"latency sigma {sigma:g}")
    for i, name in enumerate(NAMED):
        if p := data["points"].get(name):
            ax.scatter([0.075 if name == "halfcheetah" else 16.0], [p["ebrl_vs_best"]], marker="s^"[i], s=60,
                       label=name, zorder=3)
    ax.axhline(1.0, color="grey", lw=1, ls="--")
    ax.axhline(1.2, color="grey", lw=0.8, ls=":")
    ax.set_xscale("log")
    ax.set_xlabel("mean step latency (ms)")
    ax.set_ylabel("ebrl (defaults) / best baseline, traj/s")
    ax.set_title(f"stepping sweep, {data['machine']}")
    ax.legend(fontsize=8)
    fig.tight_layout()
    fig.savefig(path, dpi=120)
    plt.close(fig)


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    parser.add_argument("--points", default="", help="comma-separated points (default: every point)")
    parser.add_argument("--duration", type=float, default=60.0, help="measured seconds per run (after warm-up)")
    parser.add_argument("--repeat", type=int, default=1, help="rounds over the four modes per point")
    parser.add_argument("--set", action="append", default=[], dest="overrides", metavar="SECTION.KEY=VALUE")
    parser.add_argument("--json", default=str(ROOT / "benchmarks/results/stepping_sweep.json"))
    parser.add_argument("--force", action="store_true", help="measure points already in the file again")
    parser.add_argument("--plot-only", action="store_true")
    args = parser.parse_args()
    path = Path(args.json)
    machine = f"{platform.machine()}, {len(os.sched_getaffinity(0))} usable cores"
    data = json.loads(path.read_text()) if path.exists() else {"points": {}}
    data["machine"] = machine
    points = [p.strip() for p in args.points.split(",") if p.strip()] or all_points()
    for point in [] if args.plot_only else points:
        if point in data["points"] and not args.force:
            print(f"{point}: already measured (--force to repeat)", flush=True)
            continue
        print(f"{point} ...", flush=True)
        result = measure_point(point, args.duration, args.repeat, args.overrides)
        result["command"] = (f"python benchmarks/stepping_sweep.py --points {point} --duration {args.duration:g}"
                             f" --repeat {args.repeat}" + "".join(f" --set {o}" for o in args.overrides))
        result["machine"] = machine
        result["commit"] = bench.commit()
        if (previous := data["points"].get(point)) is not None:  # measured again: the earlier verdicts stay
            result["earlier"] = [*previous.get("earlier", []), {k: previous[k] for k in EARLIER_KEYS if k in previous}]
        data["points"][point] = result
        order = all_points()
        data["points"] = dict(sorted(data["points"].items(),
                                     key=lambda kv: order.index(kv[0]) if kv[0] in order else len(order)))
        if set(points) >= set(data["points"]):  # the whole sweep is this command's (not one point re-measured)
            data["command"] = (f"python benchmarks/stepping_sweep.py --force --duration {args.duration:g}"
                               f" --repeat {args.repeat}"
                               f" --points {','.join(p for p in all_points() if p in data['points'])}")
        path.parent.mkdir(parents=True, exist_ok=True)
        path.write_text(json.dumps(data, indent=2) + "\n")
        med = result["traj_per_s"]
        print(f"{point}: ebrl {med['ebrl']:.1f} traj/s, best baseline {result['best_baseline']} "
              f"{med[result['best_baseline']]:.1f} -> {result['ebrl_vs_best']:.2f}x", flush=True)
    if data["points"]:
        for name, p in data["points"].items():  # derived from what was measured: kept current for every point
            p.update(ceiling(name, machine_cores(p.get("machine", machine)), p))
        path.write_text(json.dumps(data, indent=2) + "\n")
        plot(data, path.with_suffix(".png"))
        for point in all_points():
            if p := data["points"].get(point):
                top = f", the cores allow {p['ceiling_vs_best']:.2f}x" if "ceiling_vs_best" in p else ""
                print(f"{point:14s} ebrl/best {p['ebrl_vs_best']:.2f}x (best: {p['best_baseline']}{top})")


if __name__ == "__main__":
    main()
