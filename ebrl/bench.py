"""``ebrl bench``: the same workload in several modes, interleaved, measured from the stats stream.

Each measurement is a real ``ebrl up`` run (``ebrl.testing.Run``: a subprocess with its own bus port):
after every service is live and the first policy update is published, the
bench process reads ``ebrl/stats/<run>/**`` for ``--duration`` seconds (or until
``--trajectories`` more segments are done) and takes the difference of the
counters between the first and last report of the window. Modes run
A B C D A B C D ... so that machine drift hits all alike. ``--ablations`` adds
ebrl with each mechanism flipped (``ablation_variants``).
"""

from __future__ import annotations

import json
import os
import statistics
import subprocess
import sys
import time
from pathlib import Path
from typing import Any

from ebrl import config as config_mod
from ebrl.envs.records import backend_record
from ebrl.messages import StatsReport
from ebrl.testing import Run, RunError, StatsWatcher, source

BASELINES = ("colocated", "hybrid", "async")
RUN_SETS = ("viz.report=false",)  # before the user's overrides: a measured run writes no report
# a throughput window is not ended by a target return or success rate (a mode that learns faster would
# otherwise be measured over less time, or not at all)
WINDOW_SETS = (*RUN_SETS, "run.target_return=", "run.target_success=")
# The mechanisms ``--ablations`` switches, each by its config key. A variant flips one of them from what the
# ebrl mode runs with this config: ``ebrl-no_<name>`` switches it off, ``ebrl+<name>`` on where the config
# leaves it off (the allocator is off by default, so its variant is usually ``ebrl+allocator``). Core
# rebinding under "auto" (the ebrl default) has both: ``ebrl-no_core_rebinding`` and ``ebrl+core_rebinding``
# (rebinding every step, never measured against pinning).
MECHANISMS = {
    "allocator": "alloc.enabled",
    "group_pipeline": "sim.group_pipeline",
    "overlap": "train.overlap",
    "core_rebinding": "sim.core_rebinding",
    "vectorized": "sim.vectorized",
    "lazy_render": "sim.lazy_render",
}


def commit() -> str:
    """The checkout's short commit, recorded beside each benchmark result ("" outside a git checkout)."""
    try:
        return subprocess.run(["git", "rev-parse", "--short", "HEAD"], capture_output=True, text=True,
                              cwd=Path(__file__).resolve().parent).stdout.strip()
    except OSError:
        return ""


def base_mode(variant: str) -> str:
    """The ``run.mode`` of a variant name: ``ebrl-no_overlap`` and ``ebrl+allocator`` run mode ebrl."""
    return variant.replace("+", "-").split("-")[0]


def ablation_variants(config: str, overrides: list[str]) -> dict[str, list[str]]:
    """ebrl with each mechanism flipped from what it runs with under ``config``: variant name -> overrides."""
    from ebrl.sched.modes import resolve

    cfg = config_mod.load(config, [*overrides, "run.mode=ebrl"])
    schedule = resolve(cfg)
    running = {
        "allocator": cfg.alloc.enabled,
        "group_pipeline": schedule.groups > 1,
        "overlap": schedule.overlap,
        "core_rebinding": schedule.core_rebinding,
        "vectorized": schedule.vectorized,
        "lazy_render": schedule.lazy_render,
    }
    cameras = backend_record(cfg.env.backend).cameras(cfg.env.kwargs)
    out = {}
    for name, key in MECHANISMS.items():
        if name == "lazy_render" and not cameras:
            continue  # nothing renders: the switch changes nothing
        if running[name]:
            out[f"ebrl-no_{name}"] = [f"{key}=false"]
        if name == "vectorized" and (cfg.algo.name == "grpo" or cfg.alloc.enabled):
            continue  # refused with GRPO (shared initial states) and with the allocator (per-env profiles)
        if name == "group_pipeline" and cfg.sim.groups < 2:
            continue  # one group: nothing to pipeline
        if not running[name] or (name == "core_rebinding" and schedule.rebinding_auto):  # auto: also always on
            out[f"ebrl+{name}"] = [f"{key}=true"]
    return out


def measure(config: str, mode: str, extra: list[str], duration: float, startup_timeout: float = 300.0,
            out_dir: str = "runs/bench", trajectories: int = 0, max_seconds: float = 3600.0) -> dict[str, Any]:
    """One run of ``config`` in ``mode`` (a mode or a variant name): throughput and latencies over
    ``duration`` seconds after warm-up or, with ``trajectories`` > 0, until that many more trajectory
    segments are done (at most ``max_seconds``). The run keeps a ``run.name`` given in ``extra``."""
    name = f"bench-{mode}".replace("_", "-").replace("+", "-with-")[:40]
    overrides = [f"run.mode={base_mode(mode)}", "run.iterations=0", *WINDOW_SETS, *extra]
    with Run(config, *overrides, name=name, out_dir=out_dir, stats_interval=1.0) as run, StatsWatcher(run) as stats:
        # warm: one update done, so start-up and the first compile are outside the window
        stats.wait_for(lambda: (stats.latest("train/0", "train/policy_version") or 0) >= 1, startup_timeout,
                       f"{mode}'s first policy update (warm-up)")
        if trajectories > 0:
            stats.wait_for(lambda: stats.latest_report("sim/0", "sim/segments") is not None, startup_timeout,
                           f"{mode}'s first sim report")
            first = stats.latest_report("sim/0", "sim/segments")
            t0, base = first.time, first.metrics["sim/segments"]
            stats.wait_for(lambda: stats.latest("sim/0", "sim/segments") - base >= trajectories, max_seconds,
                           f"{trajectories} trajectories of {mode}")
            t1 = stats.latest_report("sim/0", "sim/segments").time
        else:
            t0 = time.time()
            stats.wait_for(lambda: time.time() - t0 >= duration, duration + 60, f"the end of {mode}'s window")
            t1 = time.time()
    return summarize(stats.between(t0, t1), t1 - t0)


# The last update's learning diagnostics, kept with each point of a learning curve (docs/stats.md: "Stats: watching a run from any script").
TRAIN_DIAGNOSTICS = ("staleness_mean", "behave_kl", "behave_weight_mean", "behave_weight_capped", "approx_kl",
                     "clipfrac", "value_drift", "explained_variance", "adv_std", "entropy", "value_loss")


def learning_curve(config: str, overrides: list[str], name: str, timeout: float = 1800.0,
                   out_dir: str = "runs/bench") -> list[dict[str, float]]:
    """Run ``config`` to its end and return the learning curve: one point per sim stats report with
    wall seconds since launch, env steps, policy version and mean return of the last 20 episodes, and the
    latest update's ``TRAIN_DIAGNOSTICS`` then."""
    started = time.time()
    with Run(config, *RUN_SETS, *overrides, name=name, out_dir=out_dir, stats_interval=1.0) as run, \
            StatsWatcher(run) as stats:
        try:
            code = run.wait(timeout)
        except RunError:  # out of time: stopped as Ctrl-C would, keeping the curve so far
            code = run.stop(60)
    if code not in (0, 130):
        raise RuntimeError(f"{run.name}: ebrl up failed ({code}):\n{run.output}")
    curve, version, train = [], 0.0, {}
    for report in sorted(stats.reports(), key=lambda r: r.time):
        m = report.metrics
        if source(report) == "train/0":
            version = m.get("train/policy_version", version)
            train = {k: m[f"train/{k}"] for k in TRAIN_DIAGNOSTICS if f"train/{k}" in m}
        elif source(report) == "sim/0" and "sim/episode_return_mean" in m:
            curve.append({"wall_s": report.time - started, "env_steps": m["sim/env_steps"],
                          "policy_version": version, "return": m["sim/episode_return_mean"], **train})
    return curve


def _delta(reports: list[StatsReport], name: str) -> float:
    values = [r.metrics[name] for r in reports if name in r.metrics]
    return values[-1] - values[0] if len(values) > 1 else 0.0


def _span_s(reports: list[StatsReport]) -> float:
    return reports[-1].time - reports[0].time if len(reports) > 1 else 0.0


def summarize(window: dict[str, list[StatsReport]], duration: float) -> dict[str, Any]:
    sim, gen, train = window.get("sim/0", []), window.get("gen/0", []), window.get("train/0", [])
    dt = _span_s(sim) or duration
    out = {
        "window_s": dt,
        "trajectories": _delta(sim, "sim/segments"),
        "traj_per_s": _delta(sim, "sim/segments") / dt,
        "env_steps_per_s": _delta(sim, "sim/env_steps") / dt,
        "updates_per_s": _delta(train, "train/updates") / (_span_s(train) or duration),
    }
    last = sim[-1].metrics if sim else {}
    for q in ("avg", "p50", "p99"):
        out[f"chunk_latency_{q}_ms"] = last.get(f"sim/chunk_latency_{q}_ms", float("nan"))
    modes = [r.metrics["sim/core_rebinding"] for r in sim if "sim/core_rebinding" in r.metrics]
    if modes:  # sim.core_rebinding = "auto": the share of the window spent rebinding, the last trial's gain
        out["rebinding_share"] = statistics.fmean(modes)
        out["rebinding_gain"] = last.get("sim/rebinding_gain", float("nan"))
    # Busy fraction of each stage over the window (from spans, via the busy/<lane> metrics).
    def busy(reports: list[StatsReport], prefix: str) -> float:
        fractions = [sum(v for k, v in r.metrics.items() if k.startswith(prefix)) for r in reports[1:]]
        return statistics.fmean(fractions) if fractions else 0.0

    groups = max(1, sum(1 for k in last if k.startswith("busy/sim.g")))
    out["busy_sim"] = busy(sim, "busy/sim.g") / groups
    out["busy_gen"] = busy(gen, "busy/gen")
    out["busy_train"] = busy(train, "busy/train")
    out["idle_sim"], out["idle_gen"], out["idle_train"] = (1 - out["busy_sim"], 1 - out["busy_gen"],
                                                          1 - out["busy_train"])
    cores = len(os.sched_getaffinity(0))  # the cores runs may use, not every core of the host
    steps_busy = _delta(sim, "sim/step_busy_s") / dt  # cores' worth of time inside env.step
    out["useful_work_utilisation"] = min(1.0, (steps_busy + out["busy_gen"] + out["busy_train"]) / cores)
    return out


def raw_capacity(config: str, variants: dict[str, list[str]], seconds: float) -> dict[str, dict[str, Any]]:
    """The physical limit of each variant: raw env steps/s of the cores its simulation holds (measured once
    per distinct core set, before the runs, with nothing else running)."""
    from ebrl.envs import EnvSpec
    from ebrl.envs.worker import raw_steps_per_s
    from ebrl.sched.modes import resolve

    measured: dict[tuple[int, ...], float] = {}
    out = {}
    for variant, overrides in variants.items():
        cfg = config_mod.load(config, [*overrides, f"run.mode={base_mode(variant)}"])
        cores = tuple(resolve(cfg).sim_cores)
        if cores not in measured:
            print(f"raw simulator capacity of cores {list(cores)} ...", file=sys.stderr, flush=True)
            measured[cores] = raw_steps_per_s(EnvSpec.from_config(cfg.env), list(cores), seconds)
        out[variant] = {"sim_cores": list(cores), "raw_env_steps_per_s": measured[cores]}
    return out


def run(config: str, variants: dict[str, list[str]], duration: float, repeat: int, raw_seconds: float = 10.0,
        trajectories: int = 0) -> dict[str, Any]:
    """Measure every variant (name -> its ``--set`` overrides) ``repeat`` times, interleaved."""
    for overrides in variants.values():
        config_mod.load(config, overrides)  # fail fast on a bad config
    raw = raw_capacity(config, variants, raw_seconds) if raw_seconds > 0 else {}
    results: dict[str, list[dict[str, Any]]] = {m: [] for m in variants}
    for r in range(repeat):
        for variant, overrides in variants.items():
            print(f"[{r + 1}/{repeat}] {variant} ...", file=sys.stderr, flush=True)
            result = measure(config, variant, overrides, duration, trajectories=trajectories)
            if variant in raw:  # sim efficiency: achieved env steps/s over the raw capacity of sim's cores
                result.update(raw[variant])
                result["sim_efficiency"] = result["env_steps_per_s"] / raw[variant]["raw_env_steps_per_s"]
            results[variant].append(result)
    return results


def table(results: dict[str, list[dict[str, Any]]]) -> str:
    def med(mode: str, key: str) -> float:
        return statistics.median(x[key] for x in results[mode])

    baselines = [m for m in results if m in BASELINES]
    best = max(baselines, key=lambda m: med(m, "traj_per_s")) if baselines else None
    head = ("mode", "traj/s min-med-max", "env steps/s", "sim eff", "chunk ms avg/p50/p99", "idle sim/gen/train",
            "useful util", "vs best baseline")
    rows = [head]
    for mode, runs in results.items():
        traj = sorted(x["traj_per_s"] for x in runs)
        ratio = "-" if not best else (f"{med(mode, 'traj_per_s') / med(best, 'traj_per_s'):.2f}x"
                                      if med(best, "traj_per_s") > 0 else "inf" if med(mode, "traj_per_s") else "-")
        rows.append((
            mode,
            f"{traj[0]:.1f}-{statistics.median(traj):.1f}-{traj[-1]:.1f}",
            f"{med(mode, 'env_steps_per_s'):,.0f}",
            f"{med(mode, 'sim_efficiency'):.2f}" if "sim_efficiency" in runs[0] else "-",
            f"{med(mode, 'chunk_latency_avg_ms'):.0f}/{med(mode, 'chunk_latency_p50_ms'):.0f}/"
            f"{med(mode, 'chunk_latency_p99_ms'):.0f}",
            f"{med(mode, 'idle_sim'):.2f}/{med(mode, 'idle_gen'):.2f}/{med(mode, 'idle_train'):.2f}",
            f"{med(mode, 'useful_work_utilisation'):.2f}",
            ratio + (" (best)" if mode == best else ""),
        ))
    widths = [max(len(str(r[i])) for r in rows) for i in range(len(head))]
    return "\n".join("  ".join(str(c).ljust(w) for c, w in zip(r, widths)) for r in rows)


def parse_variant(item: str) -> tuple[str, list[str]]:
    """``LABEL=SECTION.KEY=VALUE[,...]`` -> (label, overrides); the label names its mode first (``hybrid+x``)."""
    label, _, sets = item.partition("=")
    if base_mode(label) not in ("ebrl", *BASELINES) or label in ("ebrl", *BASELINES) or not sets:
        raise ValueError(f"--variant {item!r}: expected LABEL=SECTION.KEY=VALUE[,...] with LABEL a mode followed by "
                         f"+ or - and a name (e.g. hybrid+vectorized=sim.vectorized=true)")
    return label, [x for x in sets.split(",") if x]


def main(config: str, modes: str, ablations: bool, duration: float, repeat: int, json_path: str,
         overrides: list[str], raw_seconds: float = 10.0, trajectories: int = 0, extra: list[str] = ()) -> int:
    names = [m.strip() for m in modes.split(",") if m.strip()]
    unknown = [m for m in names if m not in ("ebrl", *BASELINES)]
    if unknown:
        print(f"ebrl bench: unknown mode(s) {unknown}; choose from ebrl, {', '.join(BASELINES)}", file=sys.stderr)
        return 2
    try:
        parsed = [parse_variant(item) for item in extra]
    except ValueError as exc:
        print(f"ebrl bench: {exc}", file=sys.stderr)
        return 2
    try:
        variants = {name: list(overrides) for name in names}
        variants.update({label: [*overrides, *sets] for label, sets in parsed})
        if ablations:
            flips = ablation_variants(config, overrides)
            variants.update({name: [*overrides, *flip] for name, flip in flips.items()})
        results = run(config, variants, duration, repeat, raw_seconds, trajectories)
    except config_mod.ConfigError as exc:
        print(f"ebrl: config error: {exc}", file=sys.stderr)
        return 2
    if json_path:  # first: what was measured is kept whatever the printing does
        Path(json_path).parent.mkdir(parents=True, exist_ok=True)
        Path(json_path).write_text(json.dumps({
            "command": "ebrl " + " ".join(sys.argv[1:]), "machine": f"{len(os.sched_getaffinity(0))} usable cores",
            "config": config, "duration_s": duration, "trajectories": trajectories, "repeat": repeat,
            "overrides": overrides, "variants": variants, "results": results,
        }, indent=2) + "\n")
    print(table(results))
    return 0
