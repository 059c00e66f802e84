"""Action-chunk latency: step-level asynchrony with greedy core rebinding vs batch stepping.

Same environments, chunk length and step-latency distribution (HalfCheetah-v5 with
a lognormal busy-wait added to every step, seeded per env, so every policy sees
the same step latencies). Each policy runs real env worker processes; the chunk
latency of an env is the time from the chunk's start to its last step.

Beside the measurement, a discrete-event replay of the same step latencies gives
what an ideal (zero-overhead) scheduler would reach: batch stepping with the
best possible packing of each round onto the cores, and greedy rebinding
(the paper's algorithm, ebrl.sched.rebind). The measured ratio is judged
against the ideal ratio.

    python benchmarks/chunk_latency.py --envs 8 --cores 2 --sigma 0.3
"""

from __future__ import annotations

import argparse
import asyncio
import heapq
import json
import math
import os
import platform
import sys
import time
from pathlib import Path

import numpy as np

sys.path.insert(0, str(Path(__file__).resolve().parent.parent))

from ebrl import bench  # noqa: E402
from ebrl.envs import EnvSpec, EnvWorker  # noqa: E402
from ebrl.sched.rebind import CoreRebinding  # noqa: E402
from ebrl.resources.corepool import CorePool  # noqa: E402
from ebrl.sched.stepping import BatchStepping, RebindingStepping  # noqa: E402

ENV_ID = "HalfCheetah-v5"  # never terminates; 1000-step episodes outlast the benchmark


def latency_draws(seed: int, n: int, mean_ms: float, sigma: float) -> np.ndarray:
    """The step latencies env ``seed`` will add (same generator as ebrl.envs.latency.StepLatency)."""
    mu = math.log(mean_ms / 1e3) - sigma**2 / 2
    return np.random.default_rng(seed).lognormal(mu, sigma, n)


def replay_batch(lat: np.ndarray, cores: int) -> np.ndarray:
    """Ideal batch stepping: each round's steps packed longest-first onto the cores; every env of the
    chunk finishes when the last round ends. ``lat`` is [chunks, envs, K]; returns [chunks, envs]."""
    out = np.zeros(lat.shape[:2])
    for c in range(lat.shape[0]):
        t = 0.0
        for k in range(lat.shape[2]):
            loads = [0.0] * cores
            for step in sorted(lat[c, :, k], reverse=True):
                i = loads.index(min(loads))
                loads[i] += step
            t += max(loads)
        out[c] = t
    return out


def replay_rebinding(lat: np.ndarray, cores: int) -> np.ndarray:
    """Greedy core rebinding (ebrl.sched.rebind) on a fake clock; returns per-env chunk latency."""
    chunks, envs, K = lat.shape
    sched = CoreRebinding(list(range(cores)))
    for e in range(envs):
        sched.add_env(e)
    out = np.zeros((chunks, envs))
    for c in range(chunks):
        for e in range(envs):
            sched.submit_chunk(e, K)
        t, events = 0.0, []
        for e, core in sched.dispatch():
            heapq.heappush(events, (t + lat[c, e, sched.envs[e].s], e))
        while events:
            t, e = heapq.heappop(events)
            step = lat[c, e, sched.envs[e].s]
            if sched.complete(e, step):
                out[c, e] = t
            for e2, core in sched.dispatch():
                heapq.heappush(events, (t + lat[c, e2, sched.envs[e2].s], e2))
    return out


def summarize(chunk_latencies: np.ndarray) -> dict[str, float]:
    flat = np.asarray(chunk_latencies).ravel() * 1e3
    return {"avg_ms": float(flat.mean()), "p50_ms": float(np.percentile(flat, 50)),
            "p99_ms": float(np.percentile(flat, 99))}


async def measure(policy: str, args, cores: list[int]) -> np.ndarray:
    spec = EnvSpec(ENV_ID, latency="lognormal", latency_mean_ms=args.mean_ms, latency_sigma=args.sigma)
    pinned = policy == "batch_pinned"
    pool = CorePool(args.envs, cores) if policy == "rebinding" else None
    workers = [EnvWorker(spec, seed=e, core=cores[e % len(cores)] if pinned else None, pool=pool, slot=e)
               for e in range(args.envs)]
    try:
        if pool is not None:
            stepping = RebindingStepping(pool)
        else:
            stepping = BatchStepping()
            if not pinned:  # the OS spreads the workers over the same cores, no pinning
                for w in workers:
                    os.sched_setaffinity(w.proc.pid, cores)
        await asyncio.gather(*(w.reset() for w in workers))
        rng = np.random.default_rng(0)
        out = []
        for _ in range(args.warmup + args.chunks):
            actions = rng.uniform(-1, 1, (args.envs, args.chunk, 6)).astype(np.float32)
            _, latencies = await stepping.run_chunk(workers, actions)
            out.append(latencies)
        return np.asarray(out[args.warmup:])
    finally:
        for w in workers:
            w.close()


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    parser.add_argument("--envs", type=int, default=8)
    parser.add_argument("--cores", type=int, default=0, help="simulation cores (default: all usable)")
    parser.add_argument("--chunk", type=int, default=8, help="K, steps per chunk")
    parser.add_argument("--chunks", type=int, default=40, help="measured chunks per policy")
    parser.add_argument("--warmup", type=int, default=3)
    parser.add_argument("--mean-ms", type=float, default=16.0)
    parser.add_argument("--sigma", type=float, default=0.3)
    parser.add_argument("--json", default="", help="result file (default: benchmarks/results/chunk_latency_<envs>e<cores>c_s<sigma>.json)")
    args = parser.parse_args()
    usable = sorted(os.sched_getaffinity(0))
    cores = usable[:args.cores] if args.cores else usable

    measured = {}
    for policy in ("rebinding", "batch_pinned", "batch_os"):
        started = time.perf_counter()
        measured[policy] = asyncio.run(measure(policy, args, cores))
        print(f"{policy:13s} {summarize(measured[policy])}  ({time.perf_counter() - started:.0f} s)", flush=True)
    # The latencies every env drew, chunk by chunk (warm-up chunks included in the draw order).
    total = (args.warmup + args.chunks) * args.chunk
    draws = np.stack([latency_draws(e, total, args.mean_ms, args.sigma) for e in range(args.envs)])
    lat = draws.reshape(args.envs, args.warmup + args.chunks, args.chunk).transpose(1, 0, 2)[args.warmup:]
    ideal = {"rebinding": summarize(replay_rebinding(lat, len(cores))), "batch": summarize(replay_batch(lat, len(cores)))}

    best_batch = min(("batch_pinned", "batch_os"), key=lambda p: summarize(measured[p])["avg_ms"])
    m_reb, m_bat = summarize(measured["rebinding"]), summarize(measured[best_batch])
    result = {
        "command": "python benchmarks/chunk_latency.py " + " ".join(sys.argv[1:]), "commit": bench.commit(),
        "machine": f"{platform.machine()}, {os.cpu_count()} cores visible, {len(cores)} used",
        "env": ENV_ID, "envs": args.envs, "cores": len(cores), "chunk": args.chunk, "chunks": args.chunks,
        "latency": {"dist": "lognormal", "mean_ms": args.mean_ms, "sigma": args.sigma},
        "measured": {p: summarize(v) for p, v in measured.items()},
        "best_batch_baseline": best_batch,
        "ideal_replay": ideal,
        "avg_ratio": m_bat["avg_ms"] / m_reb["avg_ms"],
        "p99_ratio": m_bat["p99_ms"] / m_reb["p99_ms"],
        "ideal_avg_ratio": ideal["batch"]["avg_ms"] / ideal["rebinding"]["avg_ms"],
        "ideal_p99_ratio": ideal["batch"]["p99_ms"] / ideal["rebinding"]["p99_ms"],
    }
    result["avg_ratio_of_ideal"] = result["avg_ratio"] / result["ideal_avg_ratio"]
    result["p99_ratio_of_ideal"] = result["p99_ratio"] / result["ideal_p99_ratio"]
    path = Path(args.json or Path(__file__).parent / "results" /
                f"chunk_latency_{args.envs}e{len(cores)}c_s{args.sigma:g}.json")
    path.parent.mkdir(parents=True, exist_ok=True)
    path.write_text(json.dumps(result, indent=2) + "\n")
    print(f"chunk latency, {args.envs} envs on {len(cores)} cores, sigma {args.sigma}: rebinding vs {best_batch} "
          f"avg {result['avg_ratio']:.2f}x (ideal {result['ideal_avg_ratio']:.2f}x, {result['avg_ratio_of_ideal']:.2f} of it), "
          f"P99 {result['p99_ratio']:.2f}x (ideal {result['ideal_p99_ratio']:.2f}x, {result['p99_ratio_of_ideal']:.2f} of it)")


if __name__ == "__main__":
    main()
