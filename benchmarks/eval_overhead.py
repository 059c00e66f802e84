"""Does the eval service slow training? Trajectories/s of a run with ``[eval]`` on against the same run without.

    python benchmarks/eval_overhead.py                      # the quickstart, eval every 10 versions, 3 x 40 s
    python benchmarks/eval_overhead.py --config configs/robosuite_lift.toml --every 5 --repeat 5

The two variants run interleaved (off, on, off, on, ...) through ``ebrl.bench`` (real ``ebrl up`` runs, each
measured over ``--duration`` seconds after its first update). The eval service runs its episodes in
idle-priority worker processes on ``eval.cores``, so it should only take what training and simulation leave;
the issue's bar is that trajectories/s with eval on stay within 5 % of without. Results go to
``benchmarks/results/eval_overhead.json``.
"""

from __future__ import annotations

import argparse
import json
import os
import platform
import statistics
import sys
from pathlib import Path

sys.path.insert(0, str(Path(__file__).resolve().parent.parent))

from ebrl import bench  # noqa: E402

RESULTS = Path(__file__).resolve().parent / "results"


def main() -> int:
    p = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    p.add_argument("--config", default="configs/quickstart.toml")
    p.add_argument("--every", type=int, default=10, help="eval.every of the run with eval on")
    p.add_argument("--duration", type=float, default=40.0, help="seconds measured per run")
    p.add_argument("--repeat", type=int, default=3)
    p.add_argument("--set", action="append", default=[], dest="overrides", metavar="SECTION.KEY=VALUE")
    p.add_argument("--out", default=str(RESULTS / "eval_overhead.json"))
    args = p.parse_args()
    variants = {"ebrl": [*args.overrides, "eval.every=0"], "ebrl+eval": [*args.overrides, f"eval.every={args.every}"]}
    results = bench.run(args.config, variants, args.duration, args.repeat, raw_seconds=0)

    def med(variant: str, key: str) -> float:
        return statistics.median(r[key] for r in results[variant])

    ratio = med("ebrl+eval", "traj_per_s") / med("ebrl", "traj_per_s")
    steps_ratio = med("ebrl+eval", "env_steps_per_s") / med("ebrl", "env_steps_per_s")
    commit = bench.commit()
    out = {
        "command": "python benchmarks/eval_overhead.py " + " ".join(sys.argv[1:]),
        "machine": f"{platform.machine()}, {len(os.sched_getaffinity(0))} usable cores", "commit": commit,
        "config": args.config, "every": args.every, "duration_s": args.duration, "repeat": args.repeat,
        "overrides": args.overrides,
        "traj_per_s": {v: [r["traj_per_s"] for r in runs] for v, runs in results.items()},
        "env_steps_per_s": {v: [r["env_steps_per_s"] for r in runs] for v, runs in results.items()},
        "eval_on_vs_off": round(ratio, 3), "eval_on_vs_off_env_steps": round(steps_ratio, 3),
        "within_5_percent": ratio >= 0.95,
    }
    Path(args.out).parent.mkdir(parents=True, exist_ok=True)
    Path(args.out).write_text(json.dumps(out, indent=2) + "\n")
    for variant in variants:
        print(f"{variant:10s} traj/s {out['traj_per_s'][variant]}  env steps/s {out['env_steps_per_s'][variant]}")
    print(f"eval on / off: {ratio:.3f}x traj/s, {steps_ratio:.3f}x env steps/s "
          f"({'within' if ratio >= 0.95 else 'NOT within'} 5 %); written {args.out}")
    return 0


if __name__ == "__main__":
    sys.exit(main())
