"""Runtime adaptation: slow one stage mid-run and watch the allocator (or its absence) respond.

    python benchmarks/adaptation.py --config configs/quickstart.toml --slowdown "train=1.3@60" --duration 180

Runs the config twice, side by side: with the allocator (``alloc.enabled``) and
without it, both with the same injected slowdown (``run.slowdown``: every busy
span of that service stretched by the factor, a CPU busy-wait). From each run's
recording it reports decisions/s before and after the slowdown, and for the
allocator run every re-allocation (or revert) with how many stats reports after
the slowdown it came. Results go to benchmarks/results/adaptation_<tag>.json.
"""

from __future__ import annotations

import argparse
import json
import statistics
import sys
import time
from pathlib import Path

sys.path.insert(0, str(Path(__file__).resolve().parent.parent))

from ebrl import bench, config  # noqa: E402
from ebrl.testing import Run  # noqa: E402
from ebrl.viz import record  # noqa: E402

RESULTS = Path(__file__).resolve().parent / "results"


def run(config_path: str, name: str, overrides: list[str], duration: float, out_dir: str) -> Path:
    """Run ``config_path`` for ``duration`` seconds, stop it as Ctrl-C would; its run directory."""
    with Run(config_path, "run.iterations=0", *bench.WINDOW_SETS, *overrides, name=name, out_dir=out_dir,
             stats_interval=1.0) as up:
        time.sleep(duration)  # the run itself: the slowdown comes mid-way, and the allocator's answer (or none)
        up.stop(60)
    return up.run_dir


def analyse(run_dir: Path, chunk: int, slow_after: float) -> dict:
    rec = record.read(run_dir)
    sim = sorted((r for r in rec.stats if r.service == "sim"), key=lambda r: r.time)
    start = sim[0].time - sim[0].metrics.get("proc/uptime_s", 0.0)  # the sim service's start
    slow_at = start + slow_after
    before = [r.metrics.get("sim/env_steps_per_s", 0.0) / chunk for r in sim if slow_at - 40 <= r.time < slow_at]
    after = [r.metrics.get("sim/env_steps_per_s", 0.0) / chunk for r in sim if r.time >= slow_at + 40]
    changes = [{"kind": e.kind, "after_slowdown_s": round(e.time - slow_at, 1), "text": e.text}
               for e in rec.events if e.kind in ("realloc", "revert")]
    return {"run_dir": str(run_dir), "decisions_per_s_before": statistics.fmean(before) if before else 0.0,
            "decisions_per_s_after": statistics.fmean(after) if after else 0.0, "changes": changes}


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    parser.add_argument("--config", default="configs/quickstart.toml")
    parser.add_argument("--slowdown", default="train=1.3@60")
    parser.add_argument("--duration", type=float, default=180.0)
    parser.add_argument("--tag", default="quickstart")
    parser.add_argument("--set", action="append", default=[], metavar="SECTION.KEY=VALUE")
    args = parser.parse_args()
    cfg = config.load(args.config, args.set)
    _, _, slow_after = config.parse_slowdown(args.slowdown)
    result = {"command": "python benchmarks/adaptation.py " + " ".join(sys.argv[1:]), "config": args.config,
              "slowdown": args.slowdown}
    for variant, extra in (("alloc", ["alloc.enabled=true"]), ("static", [])):
        print(f"{variant} ...", file=sys.stderr, flush=True)
        run_dir = run(args.config, f"adapt-{variant}", [*args.set, f'run.slowdown="{args.slowdown}"', *extra],
                      args.duration, "runs/bench")
        result[variant] = analyse(run_dir, cfg.policy.chunk, slow_after)
    RESULTS.mkdir(exist_ok=True)
    path = RESULTS / f"adaptation_{args.tag}.json"
    path.write_text(json.dumps(result, indent=2) + "\n")
    print(json.dumps(result, indent=2))


if __name__ == "__main__":
    main()
