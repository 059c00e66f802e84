"""Milliseconds per SAC gradient step as the train service takes it: on its TorchPool thread, 2 x 256 networks,
batch 256, Pendulum's sizes, through the learner (replay sample included).

    python benchmarks/sac_step.py                 # the variants below, each in a fresh process

Variants: ``train.threads`` 1 or 2; ``policy.dtype`` float32 or bfloat16; and whether the process's own thread
ran torch on the same thread count first (``main_threads``: what services did before
``threads.set_threads(n, pool_only=True)``, under GNU OpenMP the pool thread's teams then run slower). Writes
benchmarks/results/sac_step.json.
"""

from __future__ import annotations

import argparse
import json
import os
import platform
import statistics
import subprocess
import sys
import tempfile
import time
from pathlib import Path

ROOT = Path(__file__).resolve().parent.parent
sys.path.insert(0, str(ROOT))
sys.path.insert(0, str(ROOT / "tests"))

VARIANTS = [  # (train threads, dtype, main thread's torch threads)
    (1, "float32", 1), (2, "float32", 2), (2, "float32", 1), (2, "bfloat16", 1)]


def one(threads_n: int, dtype: str, main_threads: int, updates: int = 12) -> float:
    """Median ms per gradient step over ``updates`` updates of 64 steps, in this process."""
    import torch

    from ebrl import threads
    from test_algorithms import pendulum_segments, sac_learner

    torch.set_num_threads(main_threads)
    torch.randn(256, 256) @ torch.randn(256, 256)  # the main thread's team, as a model's initialisation makes
    threads.set_threads(threads_n, pool_only=True)
    with tempfile.TemporaryDirectory() as run_dir:
        learner, _ = sac_learner(run_dir, "replay.batch_size=256", "policy.hidden=[256, 256]",
                                 f'policy.dtype="{dtype}"', f"train.threads={threads_n}")
        pool = threads.TorchPool("bench")
        segments = pendulum_segments(8 + 4 * updates)
        for seg in segments[:8]:
            learner.accept(seg, print)
        while learner.ready:  # past learning_starts
            pool.submit(learner.update, learner.take()).result()
        times = []
        for seg in segments[8:]:
            learner.accept(seg, print)
            if learner.ready:
                items, start = learner.take(), time.perf_counter()
                out = pool.submit(learner.update, items).result()
                times.append((time.perf_counter() - start) / out["gradient_steps"] * 1e3)
        pool.shutdown()
    return statistics.median(times)


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    parser.add_argument("--one", nargs=3, help=argparse.SUPPRESS)
    args = parser.parse_args()
    if args.one:
        print(one(int(args.one[0]), args.one[1], int(args.one[2])))
        return
    from ebrl import bench, devices

    rows = []
    for threads_n, dtype, main_threads in VARIANTS:
        out = subprocess.run([sys.executable, __file__, "--one", str(threads_n), dtype, str(main_threads)],
                             check=True, capture_output=True, text=True).stdout
        rows.append({"train_threads": threads_n, "dtype": dtype, "main_threads": main_threads,
                     "ms_per_step": round(float(out.strip().splitlines()[-1]), 2)})
        print(rows[-1], flush=True)
    path = ROOT / "benchmarks/results/sac_step.json"
    path.write_text(json.dumps({"command": "python benchmarks/sac_step.py", "commit": bench.commit(),
                                "date": time.strftime("%Y-%m-%d"), "cpu_bf16": devices.cpu_has_bf16(),
                                "machine": f"{platform.machine()}, {len(os.sched_getaffinity(0))} usable cores",
                                "rows": rows}, indent=1) + "\n")
    print(f"wrote {path}")


if __name__ == "__main__":
    main()
