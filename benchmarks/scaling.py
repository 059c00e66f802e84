"""Scale-out: throughput with 1, 2, 4 simulation hosts and 1, 2 training ranks, as real multi-host runs.

    python benchmarks/scaling.py --hosts 1,2,4 --world-sizes 1,2 --duration 15 --repeat 2

Each configuration (H sim hosts, W training ranks) is one run of several ``ebrl up`` processes on this machine:
the primary (``--only gen,train --instance 0``, ``train.world_size = W``) and H sim hosts (``--only sim
--instance k``, k = 1..H), each launcher on its own loopback port, the sim hosts connecting to the primary.
An update stays ``train.batch_size`` decisions: with more live sim hosts each env's share of an iteration
is shorter, not the batch bigger. Once rank 0 published its first update and ``--warmup`` seconds passed,
the script reads ``ebrl/stats/<run>/**`` for ``--duration`` seconds and takes each counter's difference between
the first and last report of the window: env steps/s and segments/s summed over the sim hosts, updates/s of
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
import signal
import statistics
import subprocess
import sys
import time
from pathlib import Path
from typing import Any

import psutil
import zenoh

sys.path.insert(0, str(Path(__file__).resolve().parent.parent))

from ebrl import bench, config  # noqa: E402
from ebrl.bus.endpoints import free_port  # noqa: E402

ROOT = Path(__file__).resolve().parent.parent
RESULTS = ROOT / "benchmarks" / "results"
STOP_S = 30.0  # a launcher stops its services within ebrl.launch.SHUTDOWN_S; this is the margin


def core_plan(hosts: int, per_host: int, usable: list[int]) -> dict[int, list[int]] | None:
    """Disjoint cores per host (0: the primary, 1..H: sim hosts), or None when they must share."""
    if per_host <= 0 or (hosts + 1) * per_host > len(usable):
        return None
    return {k: usable[k * per_host:(k + 1) * per_host] for k in range(hosts + 1)}


def host_command(args, run: str, k: int, port: int, primary_port: int, world: int, hosts: int,
                 cores: list[int] | None) -> list[str]:
    """``ebrl up`` for host ``k`` of the run (0: gen and train; others: one sim host each)."""
    cmd = [sys.executable, "-m", "ebrl.cli", "up", args.config, "--only", "gen,train" if k == 0 else "sim",
           "--instance", str(k)]
    sets = [f"run.name={run}", f"run.output_dir={json.dumps(str(Path(args.runs_dir) / run / f'host{k}'))}",
            f'bus.listen=["tcp/127.0.0.1:{port}"]', f"train.world_size={world}",
            "run.iterations=0", "run.target_return=1e9", "run.stats_interval=1.0", 'viz.rerun="off"',
            "viz.report=false", *args.set]
    if k > 0:
        sets.append(f'bus.connect=["tcp/127.0.0.1:{primary_port}"]')
    if cores is not None:
        sets += [f"gen.cores={cores}", f"train.cores={cores}"] if k == 0 else [f"sim.cores={cores}"]
    for item in sets:
        cmd += ["--set", item]
    return cmd


def rate(reports: list[dict[str, Any]], name: str) -> float:
    """Counter ``name`` per second between the first and last report that carry it."""
    having = [r for r in reports if name in r["metrics"]]
    if len(having) < 2:
        return 0.0
    return (having[-1]["metrics"][name] - having[0]["metrics"][name]) / (having[-1]["time"] - having[0]["time"])


def stop(launchers: list[subprocess.Popen]) -> int:
    """SIGINT every launcher, wait, and make sure none of their processes is left; returns how many had to be
    killed (0 when every process stopped on its own)."""
    started = set()
    for proc in launchers:
        try:
            started |= {p.pid for p in psutil.Process(proc.pid).children(recursive=True)}
        except psutil.NoSuchProcess:
            pass
    for proc in launchers:
        if proc.poll() is None:
            proc.send_signal(signal.SIGINT)
    for proc in launchers:
        try:
            proc.wait(STOP_S)
        except subprocess.TimeoutExpired:
            proc.kill()
            proc.wait()
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


def measure(args, hosts: int, world: int, rep: int) -> dict[str, Any]:
    """One run with ``hosts`` sim hosts and ``world`` training ranks: its throughput over the window."""
    run = f"scale-h{hosts}-w{world}-r{rep}"
    usable = sorted(os.sched_getaffinity(0))
    plan = core_plan(hosts, args.cores_per_host, usable)
    ports = [free_port() for _ in range(hosts + 1)]
    logs = Path(args.runs_dir) / run
    logs.mkdir(parents=True, exist_ok=True)
    window = bench.StatsWindow()
    conf = zenoh.Config()
    conf.insert_json5("scouting/multicast/enabled", "false")
    conf.insert_json5("connect/endpoints", json.dumps([f"tcp/127.0.0.1:{ports[0]}"]))
    launchers: list[subprocess.Popen] = []
    began = time.monotonic()
    try:
        for k in range(hosts + 1):
            cmd = host_command(args, run, k, ports[k], ports[0], world, hosts, plan and plan[k])
            with open(logs / f"launcher-{k}.log", "w") as fh:
                launchers.append(subprocess.Popen(cmd, cwd=ROOT, stdout=fh, stderr=subprocess.STDOUT,
                                                  stdin=subprocess.DEVNULL))
            if k == 0:
                time.sleep(1.0)  # the primary listens before the sim hosts connect
        with zenoh.open(conf) as session:
            session.declare_subscriber(f"ebrl/stats/{run}/**", window.on_sample)
            sims = [f"sim/{k}" for k in range(1, hosts + 1)]
            deadline = time.monotonic() + args.startup_timeout
            while ((window.latest("train/0", "train/policy_version") or 0) < 1
                   or any(window.latest(s, "sim/env_steps") is None for s in sims)):
                ended = [k for k, p in enumerate(launchers) if p.poll() is not None]
                if ended or time.monotonic() > deadline:
                    why = f"host {ended[0]} exited" if ended else f"no update after {args.startup_timeout:.0f} s"
                    tail = (logs / f"launcher-{ended[0] if ended else 0}.log").read_text()[-3000:]
                    raise RuntimeError(f"{run}: {why}; its launcher said:\n{tail}")
                time.sleep(0.2)
            warm_s = time.monotonic() - began
            time.sleep(args.warmup)
            t0 = time.time()
            time.sleep(args.duration)
            t1 = time.time()
    finally:
        leftover = stop(launchers)
    reports = window.between(t0, t1)
    return {
        "hosts": hosts, "world_size": world, "repeat": rep, "run": run,
        "cores": {("primary" if k == 0 else f"sim{k}"): c for k, c in plan.items()} if plan else "shared",
        "env_steps_per_s": sum(rate(reports.get(s, []), "sim/env_steps") for s in sims),
        "segments_per_s": sum(rate(reports.get(s, []), "sim/segments") for s in sims),
        "updates_per_s": rate(reports.get("train/0", []), "train/updates"),
        "per_host_env_steps_per_s": {s: rate(reports.get(s, []), "sim/env_steps") for s in sims},
        "first_update_after_s": round(warm_s, 1), "leftover_processes": leftover,
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
        "warmup_s": args.warmup, "duration_s": args.duration, "repeat": args.repeat, "overrides": args.set,
        "summary": rows, "runs": runs,
    }, indent=2) + "\n")
    return 1 if leftover else 0


if __name__ == "__main__":
    sys.exit(main())
