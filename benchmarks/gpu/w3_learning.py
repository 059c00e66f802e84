"""W3 on the GPU: ``ebrl up configs/bench_w3.toml`` (a 306M-parameter flow transformer on robosuite Lift camera
observations) with generation and training sharing the GPU, for a fixed wall-clock time: does its return rise?

    python benchmarks/gpu/w3_learning.py --seconds 120 --out w3_learning.json   # on a GPU machine (check.sh)

Records every train report's policy version and mean episode return (the return of the episodes that ended
in the data of that update), the stages' devices and memory, and the GPU's SM utilisation (NVML). The
verdict compares the mean return of the first and the last quarter of the updates.
"""

from __future__ import annotations

import argparse
import json
import statistics
import sys
import tempfile
import time
from pathlib import Path

sys.path.insert(0, str(Path(__file__).resolve().parent.parent.parent))

from ebrl.testing import Run, StatsWatcher  # noqa: E402


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    parser.add_argument("--config", default="configs/bench_w3.toml")
    parser.add_argument("--seconds", type=float, default=120.0, help="wall-clock after the first update")
    parser.add_argument("--set", action="append", default=[], metavar="SECTION.KEY=VALUE")
    parser.add_argument("--out", default="w3_learning.json")
    args = parser.parse_args()
    with tempfile.TemporaryDirectory() as out, \
            Run(args.config, "run.iterations=100000", 'viz.rerun="off"', *args.set, name="gpu-w3",
                out_dir=out) as run, StatsWatcher(run) as w:
        w.wait_for(lambda: (w.latest("train/0", "train/policy_version") or 0) >= 1, 240, "the first update")
        start = time.monotonic()
        while time.monotonic() - start < args.seconds:
            run.check_running("W3 learning")
            time.sleep(1.0)
        curve = [(r.metrics["train/policy_version"], r.metrics["train/episode_return_mean"], r.time)
                 for r in w.reports("train/0")
                 if "train/policy_version" in r.metrics and "train/episode_return_mean" in r.metrics]
        result = {
            "command": " ".join(["python", "benchmarks/gpu/w3_learning.py", *sys.argv[1:]]),
            "seconds": args.seconds,
            "gen": {k: w.latest("gen/0", f"gen/{k}") for k in ("cuda_device", "cuda_mem_allocated_mb")},
            "train": {k: w.latest("train/0", f"train/{k}") for k in ("cuda_device", "cuda_mem_allocated_mb")},
            "train_update_s": w.latest("train/0", "train/update_s"),
            "env_steps_per_s": w.latest("sim/0", "sim/env_steps_per_s"),
            "gpu0_sm_percent": w.values("sim/0", "gpu/0_sm_percent")[-30:],
            "curve": [{"version": v, "return": ret, "t": t - curve[0][2]} for v, ret, t in curve] if curve else [],
        }
        result["exit"] = run.stop()
    returns = [c["return"] for c in result["curve"]]
    if len(returns) >= 8:
        q = len(returns) // 4
        result["first_quarter_return"] = statistics.fmean(returns[:q])
        result["last_quarter_return"] = statistics.fmean(returns[-q:])
        result["rises"] = result["last_quarter_return"] > result["first_quarter_return"]
    print(json.dumps({k: v for k, v in result.items() if k != "curve"}, indent=1))
    Path(args.out).write_text(json.dumps(result, indent=1) + "\n")
    sys.exit(0 if result["gen"]["cuda_device"] == 0 and result["train"]["cuda_device"] == 0 else 1)


if __name__ == "__main__":
    main()
