"""Soak: resident memory of every service over a long run must stay flat after warm-up.

    python benchmarks/soak.py                                   # 30 minutes, the quickstart, never stopping early
    python benchmarks/soak.py --minutes 2 --out /tmp/soak.json  # what `make test-slow` runs

Starts a real `ebrl up` (the target return is set out of reach, so it runs for
``--minutes`` after its first stats report), records every service's
``proc/rss_mb`` from its stats reports, then stops it with SIGINT. For each service: resident memory at the end
of the warm-up (the median over the minute after ``--warmup`` of the run; less
for short runs) and at the end (the median over the last minute), the growth
between them, and the least-squares slope after warm-up in MB per hour. A
service whose memory grew more than ``--max-growth`` percent fails the soak
(exit status 1).

Results go to benchmarks/results/soak.json.
"""

from __future__ import annotations

import argparse
import json
import os
import platform
import sys
import time
from pathlib import Path

import numpy as np

sys.path.insert(0, str(Path(__file__).resolve().parent.parent))

from ebrl.testing import STARTUP_S, Run, RunError, StatsWatcher, source  # noqa: E402

ROOT = Path(__file__).resolve().parent.parent
RESULTS = Path(__file__).resolve().parent / "results"


def soak(config: str, minutes: float, warmup: float, out_dir: str, overrides: list[str]) -> dict:
    overrides = ["run.iterations=0", "run.target_return=1e12", *overrides]
    try:
        with Run(config, *overrides, name="soak", out_dir=out_dir, stats_interval=None, cwd=ROOT) as run, \
                StatsWatcher(run) as stats:
            # the soak's clock starts at the run's first stats report: start-up is no part of its minutes
            stats.wait_for(lambda: stats.reports(), STARTUP_S, "the run's first stats report")
            start = stats.reports()[0].time
            stats.wait_for(lambda: time.time() >= start + minutes * 60, minutes * 60 + 60, f"{minutes:g} minutes")
            code = run.stop(60)
    except RunError as exc:
        raise SystemExit(str(exc)) from None
    if code not in (0, 130):
        raise SystemExit(f"ebrl up failed ({code}):\n{run.output}")
    samples: dict[str, list[tuple[float, float]]] = {}
    for report in stats.reports():
        if "proc/rss_mb" in report.metrics:
            samples.setdefault(source(report), []).append((report.time - start, report.metrics["proc/rss_mb"]))
    elapsed = time.time() - start
    window = min(60.0, elapsed * 0.2)
    rows = {}
    for service, points in sorted(samples.items()):
        t = np.array([p[0] for p in points])
        rss = np.array([p[1] for p in points])
        after = t >= warmup
        if after.sum() < 3:
            continue
        warm = rss[after & (t < warmup + window)]
        end = rss[t >= t[-1] - window]
        slope = np.polyfit(t[after] / 3600, rss[after], 1)[0]  # MB per hour
        rows[service] = {"warm_mb": round(float(np.median(warm)), 1), "end_mb": round(float(np.median(end)), 1),
                         "growth_pct": round(100 * (np.median(end) / np.median(warm) - 1), 2),
                         "slope_mb_per_h": round(float(slope), 1), "samples": int(len(points))}
    return {"config": config, "minutes": round(elapsed / 60, 2), "warmup_s": warmup, "services": rows,
            "command": "python benchmarks/soak.py " + " ".join(sys.argv[1:]),
            "machine": f"{platform.machine()}, {os.cpu_count()} cores"}


def main() -> None:
    p = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    p.add_argument("--config", default="configs/quickstart.toml")
    p.add_argument("--minutes", type=float, default=30.0)
    p.add_argument("--warmup", type=float, default=None, help="seconds of warm-up (default: 20 %% of the run, at most 5 min)")
    p.add_argument("--max-growth", type=float, default=10.0, help="percent growth after warm-up that fails the soak")
    p.add_argument("--set", action="append", default=[], dest="overrides", metavar="SECTION.KEY=VALUE")
    p.add_argument("--runs-dir", default="/tmp/ebrl-soak")
    p.add_argument("--out", default=str(RESULTS / "soak.json"))
    args = p.parse_args()
    warmup = args.warmup if args.warmup is not None else min(300.0, args.minutes * 60 * 0.2)
    result = soak(args.config, args.minutes, warmup, args.runs_dir, args.overrides)
    print(f"{'service':12s} {'after warm-up MB':>17s} {'end MB':>8s} {'growth':>8s} {'slope MB/h':>11s}")
    failed = []
    for service, row in result["services"].items():
        print(f"{service:12s} {row['warm_mb']:17.1f} {row['end_mb']:8.1f} {row['growth_pct']:7.2f}% "
              f"{row['slope_mb_per_h']:11.1f}")
        if row["growth_pct"] > args.max_growth:
            failed.append(service)
    result["max_growth_pct"], result["failed"] = args.max_growth, failed
    Path(args.out).parent.mkdir(parents=True, exist_ok=True)
    Path(args.out).write_text(json.dumps(result, indent=2) + "\n")
    print(f"{result['minutes']:.1f} min; written {args.out}" + (f"; GREW: {', '.join(failed)}" if failed else ""))
    sys.exit(1 if failed else 0)


if __name__ == "__main__":
    main()
