"""CPU cost of a policy's forward pass on a service's worker thread, with and without ``ebrl.threads``.

    python benchmarks/torch_threads.py                       # batches 1, 4, 8, 16, 32; 400 calls each
    python benchmarks/torch_threads.py --batches 4 --calls 1000
    python benchmarks/torch_threads.py --pool-teams             # a pool thread's team after the main thread's

gen answers observations on a worker thread, one forward pass every few milliseconds. The process sets torch's
thread count to ``gen.threads`` (1) on its main thread. Under OpenMP that count is per OS thread, so a plain
worker thread keeps OpenMP's default (one thread per core). ``plain`` is that worker; ``TorchPool`` is
``ebrl.threads.TorchPool``, which applies the count in its thread. Each variant runs in a fresh process: the
quickstart's policy (64x64 MLP, chunk 4), one forward pass, then a 5 ms sleep (gen's cadence), for ``--calls``
calls. It reports the process's CPU time per call (all its threads: an OpenMP team spinning between calls
counts) and the wall time of the forward pass itself.

Results go to benchmarks/results/torch_threads.json.

``--pool-teams`` measures why a service's own thread keeps one torch thread (``set_threads(n, pool_only=True)``):
a 256 x 256 x 256 matrix product on a ``TorchPool`` thread of two torch threads, in a fresh process whose main
thread used two threads first, or kept one (and, for scale, one thread). Results go to
benchmarks/results/torch_threads_pool_teams.json.
"""

from __future__ import annotations

import argparse
import concurrent.futures
import json
import os
import platform
import subprocess
import sys
import time
from pathlib import Path

sys.path.insert(0, str(Path(__file__).resolve().parent.parent))

from ebrl import bench  # noqa: E402

RESULTS = Path(__file__).resolve().parent / "results"


def one(kind: str, batch: int, calls: int) -> dict[str, float]:
    """One variant in this process: CPU ms per call, and wall ms of the forward pass."""
    import torch

    from ebrl import threads
    from ebrl.config import PolicySection
    from ebrl.envs.obs import ObsLayout
    from ebrl.policies import make_policy

    threads.set_threads(1)  # what gen does on its main thread (gen.threads = 1)
    policy = make_policy(PolicySection(kind="mlp", chunk=4, hidden=[64, 64]), ObsLayout.vector(4), 1)
    policy.eval()
    pool = threads.TorchPool("bench") if kind == "TorchPool" else concurrent.futures.ThreadPoolExecutor(1)
    obs = torch.randn(batch, 4)

    def forward() -> float:
        start = time.perf_counter()
        with torch.no_grad():
            policy.act(obs)
        return time.perf_counter() - start

    for _ in range(20):
        pool.submit(forward).result()
    cpu0, walls = time.process_time(), []
    for _ in range(calls):
        walls.append(pool.submit(forward).result())
        time.sleep(0.005)
    cpu = time.process_time() - cpu0
    pool.shutdown()
    walls.sort()
    return {"cpu_ms_per_call": cpu / calls * 1e3, "forward_ms_p50": walls[len(walls) // 2] * 1e3,
            "os_threads": len(os.listdir("/proc/self/task"))}


def pool_team(main_threads: int, pool_threads: int, calls: int = 2000) -> float:
    """In this process: us per 256^3 matrix product on a TorchPool thread of ``pool_threads`` after the main
    thread ran one of its own with ``main_threads``."""
    import torch

    from ebrl import threads

    a, w = torch.randn(256, 256), torch.randn(256, 256)
    torch.set_num_threads(main_threads)
    a @ w  # the main thread's team (a model's initialisation makes one)
    threads.set_threads(pool_threads, pool_only=True)

    def run() -> float:
        for _ in range(50):
            a @ w
        start = time.perf_counter()
        for _ in range(calls):
            a @ w
        return (time.perf_counter() - start) / calls * 1e6

    return threads.TorchPool("bench").submit(run).result()


def pool_teams(args: argparse.Namespace) -> None:
    rows = []
    for main_threads, pool_threads in ((2, 2), (1, 2), (1, 1)):
        out = subprocess.run([sys.executable, __file__, "--pool-one", str(main_threads), str(pool_threads)],
                             check=True, capture_output=True, text=True).stdout
        rows.append({"main_threads": main_threads, "pool_threads": pool_threads,
                     "us_per_matmul": round(float(out.strip().splitlines()[-1]), 1)})
        print(rows[-1], flush=True)
    path = RESULTS / "torch_threads_pool_teams.json"
    path.write_text(json.dumps({"command": "python benchmarks/torch_threads.py --pool-teams", "commit": bench.commit(),
                                "machine": f"{platform.machine()}, {len(os.sched_getaffinity(0))} cores visible",
                                "rows": rows}, indent=1) + "\n")
    print(f"wrote {path}")


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    parser.add_argument("--batches", default="1,4,8,16,32")
    parser.add_argument("--calls", type=int, default=400)
    parser.add_argument("--one", nargs=2, metavar=("KIND", "BATCH"), help=argparse.SUPPRESS)
    parser.add_argument("--json", default=str(RESULTS / "torch_threads.json"))
    parser.add_argument("--pool-teams", action="store_true", help="a pool thread's team after the main thread's")
    parser.add_argument("--pool-one", nargs=2, type=int, help=argparse.SUPPRESS)
    args = parser.parse_args()
    if args.pool_one:
        print(pool_team(*args.pool_one))
        return
    if args.pool_teams:
        return pool_teams(args)
    if args.one:
        print(json.dumps(one(args.one[0], int(args.one[1]), args.calls)))
        return
    rows = []
    for batch in [int(b) for b in args.batches.split(",")]:
        row: dict = {"batch": batch}
        for kind in ("plain", "TorchPool"):
            out = subprocess.run([sys.executable, __file__, "--one", kind, str(batch), "--calls", str(args.calls)],
                                 check=True, capture_output=True, text=True).stdout
            row[kind] = json.loads(out.strip().splitlines()[-1])
        row["cpu_ratio"] = row["plain"]["cpu_ms_per_call"] / row["TorchPool"]["cpu_ms_per_call"]
        rows.append(row)
        print(f"batch {batch:3d}: CPU per call plain {row['plain']['cpu_ms_per_call']:.2f} ms, "
              f"TorchPool {row['TorchPool']['cpu_ms_per_call']:.2f} ms ({row['cpu_ratio']:.1f}x); forward p50 "
              f"{row['plain']['forward_ms_p50']:.3f} / {row['TorchPool']['forward_ms_p50']:.3f} ms", flush=True)
    import torch

    command = ("python benchmarks/torch_threads.py " + " ".join(sys.argv[1:])).strip()
    commit = bench.commit()
    machine = f"{platform.machine()}, {len(os.sched_getaffinity(0))} cores visible, torch {torch.__version__}"
    Path(args.json).write_text(json.dumps({"command": command, "commit": commit, "machine": machine, "rows": rows,
                                           "calls": args.calls}, indent=1) + "\n")
    print(f"wrote {args.json}")


if __name__ == "__main__":
    main()
