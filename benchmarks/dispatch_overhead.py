"""Per-step dispatch overhead of step-level core rebinding, idle and on a loaded machine.

Every env steps a fixed CPU cost (the ``env.latency`` wrapper with sigma 0: each step busy-waits exactly
``--step-us`` of CPU time), so the only difference between the stepping policies is what they add around a
step. Policies, run interleaved (A B A B ...) on the same cores:

* ``rebinding`` — step-level rebinding as the ``ebrl`` mode runs it (``ebrl.sched.stepping.RebindingStepping``);
* ``independent`` — each env runs its whole chunk on its own pinned worker (one request per chunk).

Reported per policy: wall time per env step on one core (``wall * cores / steps``) and the part of it that
is not the step's own CPU time (the overhead); and the rebinding overhead over ``independent``, in µs per
step: what dispatching single steps costs. ``--load N`` runs N busy-looping processes on the same cores
beside the measurement (a machine shared with generation and training).

    python benchmarks/dispatch_overhead.py --cores 2 --envs 8 --step-us 200
    python benchmarks/dispatch_overhead.py --cores 2 --envs 8 --step-us 200 --load 2
"""

from __future__ import annotations

import argparse
import asyncio
import json
import multiprocessing as mp
import os
import platform
import statistics
import sys
import time
from pathlib import Path

import numpy as np

sys.path.insert(0, str(Path(__file__).resolve().parent.parent))

from ebrl import bench  # noqa: E402
from ebrl.envs import EnvSpec, EnvWorker  # noqa: E402
from ebrl.resources.corepool import CorePool  # noqa: E402
from ebrl.sched.stepping import IndependentStepping, RebindingStepping  # noqa: E402

ENV_ID = "InvertedPendulum-v5"  # ~20 µs of physics per step; the busy-wait sets the rest


def _hog(cores: list[int]) -> None:
    os.sched_setaffinity(0, cores)
    while True:
        pass


async def one_round(policy: str, args, cores: list[int]) -> dict[str, float]:
    spec = EnvSpec(ENV_ID, latency="lognormal", latency_mean_ms=args.step_us / 1e3, latency_sigma=0.0)
    pool = CorePool(args.envs, cores) if policy == "rebinding" else None
    workers = [EnvWorker(spec, seed=e, core=None if pool else cores[e % len(cores)], pool=pool, slot=e)
               for e in range(args.envs)]
    try:
        if pool is not None:
            stepping = RebindingStepping(pool)
        else:
            stepping = IndependentStepping()
        await asyncio.gather(*(w.reset() for w in workers))
        rng = np.random.default_rng(0)
        act_dim = 1
        for _ in range(args.warmup):
            await stepping.run_chunk(workers, rng.uniform(-1, 1, (args.envs, args.chunk, act_dim)).astype(np.float32))
        steps, busy = 0, 0.0
        start = time.perf_counter()
        for _ in range(args.chunks):
            results, _ = await stepping.run_chunk(
                workers, rng.uniform(-1, 1, (args.envs, args.chunk, act_dim)).astype(np.float32))
            steps += sum(r.steps for r in results)
            busy += sum(r.busy_s for r in results)
        wall = time.perf_counter() - start
    finally:
        for w in workers:
            w.close()
    per_step = wall * len(cores) / steps
    return {"wall_per_step_us": per_step * 1e6, "busy_per_step_us": busy / steps * 1e6,
            "overhead_per_step_us": (per_step - busy / steps) * 1e6, "steps": steps}


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    parser.add_argument("--envs", type=int, default=8)
    parser.add_argument("--cores", type=int, default=0, help="simulation cores (default: all usable)")
    parser.add_argument("--chunk", type=int, default=8, help="K, steps per chunk")
    parser.add_argument("--chunks", type=int, default=150, help="measured chunks per round")
    parser.add_argument("--warmup", type=int, default=5)
    parser.add_argument("--rounds", type=int, default=3, help="interleaved rounds per policy")
    parser.add_argument("--step-us", type=float, default=200.0, help="CPU cost of one env step (µs)")
    parser.add_argument("--load", type=int, default=0, help="busy-looping processes on the same cores")
    parser.add_argument("--label", default="", help="a name for this implementation in the result file")
    parser.add_argument("--json", default="", help="result file (default: benchmarks/results/"
                                                   "dispatch_overhead_<label>_load<N>.json)")
    args = parser.parse_args()
    usable = sorted(os.sched_getaffinity(0))
    cores = usable[:args.cores] if args.cores else usable
    hogs = [mp.Process(target=_hog, args=(cores,), daemon=True) for _ in range(args.load)]
    for h in hogs:
        h.start()
    rounds: dict[str, list[dict[str, float]]] = {"rebinding": [], "independent": []}
    try:
        for r in range(args.rounds):
            for policy in rounds:
                out = asyncio.run(one_round(policy, args, cores))
                rounds[policy].append(out)
                print(f"round {r} {policy:12s} wall/step {out['wall_per_step_us']:7.1f} µs, "
                      f"overhead {out['overhead_per_step_us']:6.1f} µs", flush=True)
    finally:
        for h in hogs:
            h.kill()
    med = {p: {k: statistics.median(o[k] for o in v) for k in v[0]} for p, v in rounds.items()}
    extra = med["rebinding"]["wall_per_step_us"] - med["independent"]["wall_per_step_us"]
    result = {
        "command": "python benchmarks/dispatch_overhead.py " + " ".join(sys.argv[1:]),
        "commit": bench.commit(), "label": args.label,
        "machine": f"{platform.machine()}, {os.cpu_count()} cores visible, {len(cores)} used",
        "env": ENV_ID, "envs": args.envs, "cores": len(cores), "chunk": args.chunk, "chunks": args.chunks,
        "step_us": args.step_us, "load_processes": args.load,
        "median": med, "rounds": rounds,
        "rebinding_extra_per_step_us": extra,
    }
    path = Path(args.json or Path(__file__).parent / "results" /
                f"dispatch_overhead_{args.label or 'run'}_load{args.load}.json")
    path.parent.mkdir(parents=True, exist_ok=True)
    path.write_text(json.dumps(result, indent=2) + "\n")
    print(f"rebinding costs {extra:.1f} µs per step over whole pinned chunks "
          f"({args.envs} envs, {len(cores)} cores, {args.step_us:g} µs steps, load {args.load}) -> {path}")


if __name__ == "__main__":
    main()
