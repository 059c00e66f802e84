"""Learning parity: does ``ebrl`` (defaults) learn as well as ``colocated``, and how much sooner?

    python benchmarks/learning_parity.py --config configs/quickstart.toml --iterations 150 --seeds 0,1,2,3,4
    python benchmarks/learning_parity.py --config configs/quickstart.toml --set env.id=Hopper-v5 --name parity_hopper
    python benchmarks/learning_parity.py --config configs/bench_halfcheetah.toml --seeds 0,1,2 --name staleness_hc \
        --variant s0=ebrl:algo.max_staleness=0 --variant s1=ebrl:algo.max_staleness=1 ...

Every run is a real ``ebrl up`` (``ebrl.bench.learning_curve``) of the same config for the same number of
updates; one update consumes ``train.batch_size`` decisions of ``policy.chunk`` env steps in every mode, so
the env-step budget is the same. The modes are interleaved seed by seed on one machine. Per run and as
medians over seeds it reports:

* ``final_return`` -- the mean of the last 5 reports' return (mean of the last 20 episodes) at the budget;
* ``best_return`` -- the best report;
* ``wall_s`` -- wall-clock seconds from launch to the end of the budget;
* ``to_target_s`` -- wall-clock seconds to the first report at or above ``--target`` (default: the config's
  ``run.target_return``; None where a run never got there);
* the learning diagnostics of the updates (``ebrl.bench.TRAIN_DIAGNOSTICS``: staleness, KL to the behaviour
  policy, importance weights, clip fraction, critic drift...), averaged over the run.

``verdict`` compares the first mode with the second (default ebrl against colocated): the median final returns
(parity: the first within 3 % of the second or above it, which a ratio >= 0.97 says where the second is
positive; a task whose returns are still around 0 at the budget has no meaningful ratio, nan, and is judged
by the difference) and the ratio of the median wall-clock to the budget (target: <= 0.65).

Runs are kept in ``benchmarks/results/NAME.json`` as they finish; a run already there for the same config,
overrides and budget is not run again (``--force`` runs it again), so a sweep can go on across sessions.
The plot (``NAME.png``) shows every run's return against wall-clock time, and the KL to the behaviour policy
and the clip fraction against updates.
"""

from __future__ import annotations

import argparse
import json
import math
import statistics
import sys
from pathlib import Path
from typing import Any

sys.path.insert(0, str(Path(__file__).resolve().parent.parent))

from ebrl import bench, config  # noqa: E402

RESULTS = Path(__file__).resolve().parent / "results"
PARITY_RETURN = 0.97  # ebrl's median final return at least 97 % of colocated's
PARITY_WALL = 0.65  # ... in at most 65 % of its wall-clock time


def run_summary(curve: list[dict[str, Any]], target: float) -> dict[str, Any]:
    """What one run's curve says: final (mean of the last 5 reports), best, wall-clock, time to target,
    and each learning diagnostic averaged over the run's reports."""
    if not curve:
        raise ValueError("the run reported no returns")
    reached = next((p["wall_s"] for p in curve if p["return"] >= target), None)
    out: dict[str, Any] = {"final_return": statistics.fmean(p["return"] for p in curve[-5:]),
                           "best_return": max(p["return"] for p in curve), "wall_s": curve[-1]["wall_s"],
                           "env_steps": curve[-1]["env_steps"], "to_target_s": reached}
    for key in bench.TRAIN_DIAGNOSTICS:
        values = [p[key] for p in curve if key in p and math.isfinite(p[key])]
        if values:
            out[f"mean_{key}"] = statistics.fmean(values)
    return out


def median_or_none(values: list[float | None]) -> float | None:
    """Median over the runs; a run that never reached the target counts as infinitely slow (None if the
    median run did not reach it)."""
    ordered = sorted(math.inf if v is None else v for v in values)
    if not ordered:
        return None
    m = statistics.median(ordered)
    return None if math.isinf(m) else m


def summarize(runs: dict[str, dict[str, dict]], modes: list[str]) -> dict[str, Any]:
    """Medians per mode over the seeds each mode has, and the verdict of modes[0] against modes[1]."""
    summary: dict[str, Any] = {}
    for mode in modes:
        per = list(runs.get(mode, {}).values())
        if not per:
            continue
        summary[mode] = {"seeds": len(per), "to_target_s": median_or_none([r["to_target_s"] for r in per]),
                         **{k: statistics.median(r[k] for r in per)
                            for k in ("final_return", "best_return", "wall_s", "env_steps")}}
        summary[mode]["reached_target"] = sum(r["to_target_s"] is not None for r in per)
        for key in bench.TRAIN_DIAGNOSTICS:
            values = [r[f"mean_{key}"] for r in per if f"mean_{key}" in r]
            if values:
                summary[mode][f"mean_{key}"] = statistics.median(values)
    a, b = modes[0], modes[1] if len(modes) > 1 else None
    if b and a in summary and b in summary:
        ra, rb = summary[a], summary[b]
        ratio = ra["final_return"] / rb["final_return"] if rb["final_return"] > 0 else math.nan
        # within 3 % of the second's return, or above it (for a negative return too)
        parity = ra["final_return"] >= rb["final_return"] - (1 - PARITY_RETURN) * abs(rb["final_return"])
        wall = ra["wall_s"] / rb["wall_s"]
        summary["verdict"] = {
            "modes": [a, b], "final_return_ratio": ratio, "wall_ratio": wall,
            "to_target_ratio": (ra["to_target_s"] / rb["to_target_s"]
                                if ra["to_target_s"] and rb["to_target_s"] else None),
            "parity": bool(parity), "faster": bool(wall <= PARITY_WALL),
            "seeds": min(ra["seeds"], rb["seeds"])}
    return summary


def plot(data: dict[str, Any], path: Path) -> None:
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    fig, (ax, kl, clip) = plt.subplots(1, 3, figsize=(15, 4))
    colors = dict(zip(data["modes"], ("tab:blue", "tab:orange", "tab:green", "tab:red", "tab:purple")))
    for mode, by_seed in data["curves"].items():
        for i, (seed, curve) in enumerate(sorted(by_seed.items())):
            label = mode if i == 0 else None
            color = colors.get(mode, "grey")
            ax.plot([p["wall_s"] for p in curve], [p["return"] for p in curve], color=color, alpha=0.7, lw=1.1,
                    label=label)
            for panel, key in ((kl, "behave_kl"), (clip, "clipfrac")):
                pts = [(p["policy_version"], p[key]) for p in curve if key in p]
                if pts:
                    panel.plot(*zip(*pts), color=color, alpha=0.6, lw=0.9, label=label)
    if data.get("target") is not None and math.isfinite(data["target"]):
        ax.axhline(data["target"], color="grey", ls=":", lw=1)
    ax.set_xlabel("wall-clock seconds since launch")
    ax.set_ylabel("mean return (last 20 episodes)")
    ax.set_title(f"{data['name']}: {data['iterations']} updates, {data['env_step_budget']:,} env steps")
    kl.set_xlabel("policy version")
    kl.set_ylabel("KL(pi_behave || pi_prox), last update")
    clip.set_xlabel("policy version")
    clip.set_ylabel("clip fraction, last update")
    for panel in (ax, kl, clip):
        panel.legend(fontsize=8)
    fig.tight_layout()
    fig.savefig(path, dpi=100)
    plt.close(fig)


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    parser.add_argument("--config", default="configs/quickstart.toml")
    parser.add_argument("--modes", default="ebrl,colocated", help="the first is compared with the second")
    parser.add_argument("--iterations", type=int, default=150, help="updates per run (the env-step budget)")
    parser.add_argument("--seeds", default="0,1,2,3,4")
    parser.add_argument("--target", type=float, default=None, help="return for to_target_s (default: the "
                        "config's run.target_return)")
    parser.add_argument("--set", action="append", default=[], dest="overrides", metavar="SECTION.KEY=VALUE",
                        help="a config override for every run")
    parser.add_argument("--mode-set", action="append", default=[], metavar="MODE:SECTION.KEY=VALUE",
                        help="an override for one mode's runs only (e.g. ebrl:train.overlap=false)")
    parser.add_argument("--variant", action="append", default=[], metavar="LABEL=MODE[:KEY=VALUE,...]",
                        help="compare labelled variants instead of --modes, e.g. s0=ebrl:algo.max_staleness=0 "
                        "(the staleness sweep); the first is compared with the second")
    parser.add_argument("--name", default="", help="results file name (default: parity_<config stem>)")
    parser.add_argument("--out", default=str(RESULTS))
    parser.add_argument("--force", action="store_true", help="run again the runs already in the file")
    args = parser.parse_args()
    cfg = config.load(args.config, args.overrides)
    name = args.name or f"parity_{Path(args.config).stem}"
    out = Path(args.out)
    out.mkdir(parents=True, exist_ok=True)
    path = out / f"{name}.json"
    modes = [m.strip() for m in args.modes.split(",") if m.strip()]
    mode_of = {m: m for m in modes}  # label -> run.mode
    mode_sets: dict[str, list[str]] = {m: [] for m in modes}
    if args.variant:
        modes, mode_of, mode_sets = [], {}, {}
        for item in args.variant:
            label, _, rest = item.partition("=")
            mode, _, sets = rest.partition(":")
            if not label or not mode or label in mode_of:
                raise SystemExit(f"--variant {item!r}: LABEL=MODE[:KEY=VALUE,...] with a new LABEL")
            modes.append(label)
            mode_of[label], mode_sets[label] = mode, [x for x in sets.split(",") if x]
    for item in args.mode_set:
        mode, _, override = item.partition(":")
        if mode not in mode_sets or not override:
            raise SystemExit(f"--mode-set {item!r}: MODE:SECTION.KEY=VALUE with MODE one of {', '.join(modes)}")
        mode_sets[mode].append(override)
    seeds = [int(s) for s in args.seeds.split(",") if s.strip()]
    target = args.target if args.target is not None else cfg.run.target_return
    budget = args.iterations * cfg.train.batch_size * cfg.policy.chunk
    setup = {"config": args.config, "overrides": args.overrides, "mode_overrides": mode_sets, "run_modes": mode_of,
             "iterations": args.iterations, "env_step_budget": budget}
    data: dict[str, Any] = json.loads(path.read_text()) if path.exists() else {}
    if any(data.get(k) != v for k, v in setup.items()):
        if data:
            print(f"{path}: other settings there; starting it again", file=sys.stderr)
        data = {}
    data.update(setup, name=name, modes=modes, target=target)
    data.setdefault("runs", {})
    data.setdefault("curves", {})
    for seed in seeds:
        for mode in modes:
            if str(seed) in data["runs"].get(mode, {}) and not args.force:
                continue
            print(f"{mode}, seed {seed}: {args.iterations} updates ({budget:,} env steps) ...", file=sys.stderr,
                  flush=True)
            curve = bench.learning_curve(args.config, [*args.overrides, *mode_sets[mode],
                                                       f"run.mode={mode_of[mode]}",
                                                       f"run.iterations={args.iterations}",
                                                       "run.target_return=1e9", f"run.seed={seed}"],
                                         name=f"parity-{mode_of[mode]}")
            data["runs"].setdefault(mode, {})[str(seed)] = run_summary(curve, target)
            data["curves"].setdefault(mode, {})[str(seed)] = curve
            data["summary"] = summarize(data["runs"], modes)
            data["command"] = "python benchmarks/learning_parity.py " + " ".join(sys.argv[1:])
            data["commit"] = bench.commit()
            tmp = path.with_suffix(".tmp")
            tmp.write_text(json.dumps(data, indent=1) + "\n")
            tmp.replace(path)
            r = data["runs"][mode][str(seed)]
            print(f"  final {r['final_return']:.1f}, best {r['best_return']:.1f}, {r['wall_s']:.0f} s, "
                  f"to target {r['to_target_s']}", file=sys.stderr, flush=True)
    if data["runs"]:
        summary = summarize(data["runs"], modes)  # also when every run was there already (a new verdict rule)
        if summary != data.get("summary"):
            data["summary"] = summary
            tmp = path.with_suffix(".tmp")
            tmp.write_text(json.dumps(data, indent=1) + "\n")
            tmp.replace(path)
        plot(data, path.with_suffix(".png"))
    print(json.dumps(data.get("summary", {}), indent=2))


if __name__ == "__main__":
    main()
