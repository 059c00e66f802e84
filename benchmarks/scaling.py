"""Scale-out: throughput with 1, 2, 4 simulation hosts and 1, 2 training ranks, as real multi-host runs.

    python benchmarks/scaling.py --hosts 1,2,4 --world-sizes 1,2 --duration 15 --repeat 2

Each configuration (H sim hosts, W training ranks) is one run of several ``ebrl up`` processes on this machine:
the primary (``--only gen,train --instance 0``, ``train.world_size = W``) and H sim hosts (``--only sim
--instance k``, k = 1..H), each launcher on its own loopback port, the sim hosts connecting to the primary.
An update stays ``train.batch_size`` decisions: with more live sim hosts each env's share of an iteration
is shorter, not the batch bigger. Once rank 0 published its first update and ``--warmup`` seconds passed,
the script reads ``ebrl/stats/<run>/**`` for ``--duration`` seconds (longer where rank 0 has not finished
``--min-updates`` updates in the window yet) and takes each counter's difference between the first and last
report of the window: env steps/s and segments/s summed over the sim hosts, updates/s of
rank 0. Configurations run interleaved (all of them, then all again for ``--repeat``) so that drift of a shared
machine hits all alike.

``--cores-per-host C`` pins each sim host to its own C cores (``sim.cores``) and the primary to its own C
(``gen.cores``, ``train.cores``) when the machine has (H + 1) x C usable cores; otherwise the hosts share
every core, which the table and the JSON say. On a 2-core machine they always share: the numbers then show
what more hosts and ranks cost on the same cores, not scale-out, which needs cores (or machines) per host.
Writes benchmarks/results/scaling.json.
"""

from __future__ import annotations

import argparse
import json
import os
import statistics
import sys
import time
from pathlib import Path
from typing import Any

import psutil

sys.path.insert(0, str(Path(__file__).resolve().parent.parent))

from ebrl import config  # noqa: E402
from ebrl.bus import auth  # noqa: E402
from ebrl.messages import StatsReport  # noqa: E402
from ebrl.testing import Run, StatsWatcher  # noqa: E402

ROOT = Path(__file__).resolve().parent.parent
RESULTS = ROOT / "benchmarks" / "results"
STOP_S = 30.0  # a launcher stops its services within ebrl.supervisor.SHUTDOWN_S; this is the margin


def core_plan(hosts: int, per_host: int, usable: list[int]) -> dict[int, list[int]] | None:
    """Disjoint cores per host (0: the primary, 1..H: sim hosts), or None when they must share."""
    if per_host <= 0 or (hosts + 1) * per_host > len(usable):
        return None
    return {k: usable[k * per_host:(k + 1) * per_host] for k in range(hosts + 1)}


def host_run(args, run: str, k: int, primary: Run | None, world: int, cores: list[int] | None) -> Run:
    """``ebrl up`` for host ``k`` of the run (0, the primary: gen and train; others: one sim host each, joining
    the primary's bus); its launcher's output goes to ``launcher-<k>.log`` beside the hosts' run directories."""
    out_dir = Path(args.runs_dir) / run / f"host{k}"
    sets = [f"train.world_size={world}", "run.iterations=0", "run.target_return=1e9", 'viz.rerun="off"',
            "viz.report=false", f'bus.secret_file="{Path(args.runs_dir).resolve() / run / auth.FILENAME}"', *args.set]
    if primary is not None:
        sets.append(f'bus.connect=["{primary.endpoint}"]')
    if cores is not None:
        sets += [f"gen.cores={cores}", f"train.cores={cores}"] if k == 0 else [f"sim.cores={cores}"]
    return Run(args.config, *sets, name=run, out_dir=out_dir, stats_interval=1.0, cwd=ROOT,
               args=["--only", "gen,train" if k == 0 else "sim", "--instance", str(k)],
               log=Path(args.runs_dir) / run / f"launcher-{k}.log")


def rate(reports: list[StatsReport], name: str) -> float:
    """Counter ``name`` per second between the first and last report that carry it."""
    having = [r for r in reports if name in r.metrics]
    if len(having) < 2:
        return 0.0
    return (having[-1].metrics[name] - having[0].metrics[name]) / (having[-1].time - having[0].time)


def stop(launchers: list[Run]) -> int:
    """SIGINT every launcher, wait, and make sure none of their processes is left; returns how many had to be
    killed (0 when every process stopped on its own)."""
    started = set()
    for run in launchers:
        try:
            started |= {p.pid for p in psutil.Process(run.proc.pid).children(recursive=True)}
        except psutil.NoSuchProcess:
            pass
    for run in launchers:
        run.interrupt()
    for run in launchers:
        run.stop(STOP_S)
    left = []
    for pid in started:
        try:
            left.append(psutil.Process(pid))
        except psutil.NoSuchProcess:
            pass
    _, alive = psutil.wait_procs(left, timeout=5)
    for p in alive:
        print(f"scaling: process {p.pid} ({' '.join(p.cmdline()[:4])}) outlived its launcher; killing it",
              file=sys.stderr)
        p.kill()
    return len(alive)


def grew(reports: list[StatsReport], name: str, by: float) -> bool:
    """Did counter ``name`` grow by at least ``by`` between the first and last of ``reports``?"""
    values = [r.metrics[name] for r in reports if name in r.metrics]
    return len(values) > 1 and values[-1] - values[0] >= by


def measure(args, hosts: int, world: int, rep: int) -> dict[str, Any]:
    """One run with ``hosts`` sim hosts and ``world`` training ranks: its throughput over the window."""
    run = f"scale-h{hosts}-w{world}-r{rep}"
    usable = sorted(os.sched_getaffinity(0))
    plan = core_plan(hosts, args.cores_per_host, usable)
    (Path(args.runs_dir) / run).mkdir(parents=True, exist_ok=True)
    auth.ensure(Path(args.runs_dir) / run / auth.FILENAME)  # one secret for every host of the run (bus.auth)
    sims = [f"sim/{k}" for k in range(1, hosts + 1)]
    launchers: list[Run] = []
    began = time.monotonic()
    try:
        primary = host_run(args, run, 0, None, world, plan and plan[0])
        launchers.append(primary)
        primary.wait_for_line(f"run {run}: ")  # its first line: the primary's bus is open for the sim hosts
        for k in range(1, hosts + 1):
            launchers.append(host_run(args, run, k, primary, world, plan and plan[k]))

        def all_running() -> None:
            for host in launchers:
                host.check_running(f"{run} to measure")

        with StatsWatcher(primary) as stats:

            def warm() -> bool:
                all_running()
                return ((stats.latest("train/0", "train/policy_version") or 0) >= 1
                        and all(stats.latest(s, "sim/env_steps") is not None for s in sims))

            stats.wait_for(warm, args.startup_timeout, "the first update and every sim host's report")
            warm_s = time.monotonic() - began
            t0 = time.time() + args.warmup

            def window_done() -> bool:
                """At least --duration s, and every counter moved inside the window (a loaded machine may take
                longer for one update than --duration)."""
                all_running()
                now = time.time()
                reports = stats.between(t0, now)
                return (now - t0 >= args.duration
                        and grew(reports.get("train/0", []), "train/updates", args.min_updates)
                        and all(grew(reports.get(s, []), "sim/env_steps", 1) for s in sims))

            stats.wait_for(window_done, args.warmup + args.duration + args.startup_timeout,
                           f"a window of {args.duration:g} s with {args.min_updates} update(s) of rank 0")
            t1 = time.time()
    finally:
        leftover = stop(launchers)
    reports = stats.between(t0, t1)
    return {
        "hosts": hosts, "world_size": world, "repeat": rep, "run": run,
        "cores": {("primary" if k == 0 else f"sim{k}"): c for k, c in plan.items()} if plan else "shared",
        "env_steps_per_s": sum(rate(reports.get(s, []), "sim/env_steps") for s in sims),
        "segments_per_s": sum(rate(reports.get(s, []), "sim/segments") for s in sims),
        "updates_per_s": rate(reports.get("train/0", []), "train/updates"),
        "per_host_env_steps_per_s": {s: rate(reports.get(s, []), "sim/env_steps") for s in sims},
        "window_s": round(t1 - t0, 1), "first_update_after_s": round(warm_s, 1), "leftover_processes": leftover,
    }


def summarize(runs: list[dict[str, Any]]) -> list[dict[str, Any]]:
    """Per (H, W): the median of the repeats (and their range), and its ratio to H = 1, W = 1."""
    keys = ("env_steps_per_s", "segments_per_s", "updates_per_s")
    rows = []
    for hosts, world in dict.fromkeys((r["hosts"], r["world_size"]) for r in runs):
        mine = [r for r in runs if (r["hosts"], r["world_size"]) == (hosts, world)]
        row = {"hosts": hosts, "world_size": world, "repeats": len(mine),
               "cores": mine[0]["cores"] if all(r["cores"] == mine[0]["cores"] for r in mine) else "mixed"}
        for key in keys:
            values = sorted(r[key] for r in mine)
            row[key] = statistics.median(values)
            row[f"{key}_min_max"] = [values[0], values[-1]]
        rows.append(row)
    base = next((r for r in rows if (r["hosts"], r["world_size"]) == (1, 1)), None)
    for row in rows:
        for key in keys:
            row[f"{key}_ratio"] = row[key] / base[key] if base and base[key] else None
    return rows


def table(rows: list[dict[str, Any]]) -> str:
    def ratio(x: float | None) -> str:
        return "-" if x is None else f"{x:.2f}x"

    head = ("H sim hosts", "W ranks", "cores", "env steps/s", "segments/s", "updates/s", "env steps vs H1W1",
            "updates vs H1W1")
    out = [head]
    for r in rows:
        out.append((str(r["hosts"]), str(r["world_size"]), "shared" if r["cores"] == "shared" else "disjoint",
                    f"{r['env_steps_per_s']:,.0f}", f"{r['segments_per_s']:.1f}", f"{r['updates_per_s']:.2f}",
                    ratio(r["env_steps_per_s_ratio"]), ratio(r["updates_per_s_ratio"])))
    widths = [max(len(row[i]) for row in out) for i in range(len(head))]
    return "\n".join("  ".join(c.ljust(w) for c, w in zip(row, widths)) for row in out)


def main() -> int:
    parser = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    parser.add_argument("--config", default="configs/quickstart.toml")
    parser.add_argument("--hosts", default="1,2,4", help="numbers of sim hosts H to measure")
    parser.add_argument("--world-sizes", default="1,2", help="training ranks W (train.world_size) to measure")
    parser.add_argument("--cores-per-host", type=int, default=0,
                        help="disjoint cores per host when the machine has (H + 1) x C; 0: every host shares all")
    parser.add_argument("--warmup", type=float, default=5.0, help="seconds after the first update, not measured")
    parser.add_argument("--duration", type=float, default=15.0, help="seconds measured per configuration")
    parser.add_argument("--min-updates", type=int, default=1,
                        help="the window goes on past --duration until rank 0 finished this many updates in it")
    parser.add_argument("--repeat", type=int, default=2, help="rounds over every configuration (interleaved)")
    parser.add_argument("--startup-timeout", type=float, default=240.0)
    parser.add_argument("--set", action="append", default=[], metavar="SECTION.KEY=VALUE",
                        help="extra config override for every host")
    parser.add_argument("--runs-dir", default="runs/scaling", help="run directories and launcher logs")
    parser.add_argument("--out", default=str(RESULTS / "scaling.json"))
    args = parser.parse_args()
    hosts = [int(h) for h in args.hosts.split(",")]
    worlds = [int(w) for w in args.world_sizes.split(",")]
    for h in hosts:  # fail fast on a bad config, before any process starts
        for w in worlds:
            try:
                config.load(args.config, [f"train.world_size={w}", *args.set])
            except config.ConfigError as exc:
                print(f"scaling: H={h}, W={w}: config error: {exc}", file=sys.stderr)
                return 2
    usable = sorted(os.sched_getaffinity(0))
    if any(core_plan(h, args.cores_per_host, usable) is None for h in hosts):
        print(f"scaling: {len(usable)} usable cores: "
              + ("no --cores-per-host, so" if args.cores_per_host <= 0 else
                 f"too few for {args.cores_per_host} per host at H = {max(hosts)}, so")
              + " hosts share every core where marked 'shared'", file=sys.stderr)
    load_before = os.getloadavg()
    runs = []
    for rep in range(args.repeat):
        for h in hosts:
            for w in worlds:
                print(f"[{rep + 1}/{args.repeat}] H={h} W={w} ...", file=sys.stderr, flush=True)
                runs.append(measure(args, h, w, rep))
    rows = summarize(runs)
    print(table(rows))
    leftover = sum(r["leftover_processes"] for r in runs)
    if leftover:
        print(f"scaling: {leftover} processes outlived their launchers (killed)", file=sys.stderr)
    out = Path(args.out)
    out.parent.mkdir(parents=True, exist_ok=True)
    out.write_text(json.dumps({
        "command": " ".join(["python benchmarks/scaling.py", *sys.argv[1:]]),
        "machine": {"usable_cores": len(usable), "load_average_before": load_before,
                    "load_average_after": os.getloadavg()},
        "cores_shared": any(r["cores"] == "shared" for r in runs),
        "config": args.config, "hosts": hosts, "world_sizes": worlds, "cores_per_host": args.cores_per_host,
        "warmup_s": args.warmup, "duration_s": args.duration, "min_updates": args.min_updates,
        "repeat": args.repeat, "overrides": args.set,
        "summary": rows, "runs": runs,
    }, indent=2) + "\n")
    return 1 if leftover else 0


if __name__ == "__main__":
    sys.exit(main())
