"""Camera observations: env steps/s of robosuite Lift with the camera rendered once per chunk vs every step.

    python benchmarks/camera_obs.py                        # ~1 min on one core
    python benchmarks/camera_obs.py --sizes 64 84 --chunk 8 --seconds 5 --repeat 2

One env worker pinned to one core runs action chunks of K random actions. "per
chunk" is how EBRL steps: the worker asks the env to render only the
observation that is read (the chunk's last, or an episode's final one);
"every step" renders after each step, as a robosuite env does by itself (and as
any stepping that treats each step as the end of a chunk would). The variants
alternate (A B A B) for ``--repeat`` rounds; the table shows the median.

Results go to benchmarks/results/camera_obs.json.
"""

from __future__ import annotations

import argparse
import asyncio
import json
import os
import platform
import statistics
import sys
import time
from pathlib import Path

import numpy as np

sys.path.insert(0, str(Path(__file__).resolve().parent.parent))

from ebrl.envs import EnvSpec, EnvWorker  # noqa: E402

RESULTS = Path(__file__).resolve().parent / "results"


async def steps_per_s(worker: EnvWorker, chunk: int, every_step: bool, seconds: float, rng) -> float:
    steps, start = 0, time.perf_counter()
    while time.perf_counter() - start < seconds:
        actions = rng.uniform(-1, 1, (chunk, 7)).astype(np.float32)
        if every_step:
            for k in range(chunk):
                steps += (await worker.chunk(actions[k:k + 1], observe=True)).steps
        else:
            steps += (await worker.chunk(actions)).steps
    return steps / (time.perf_counter() - start)


async def measure(args) -> dict:
    rng = np.random.default_rng(0)
    core = sorted(os.sched_getaffinity(0))[0]
    rows = []
    for size in args.sizes:
        spec = EnvSpec(args.task, backend="robosuite", max_episode_steps=200,
                       kwargs={"obs": "rgb", "image_size": size})
        worker = EnvWorker(spec, seed=0, core=core)
        try:
            await worker.reset()
            await steps_per_s(worker, args.chunk, False, 1.0, rng)  # warm-up
            runs: dict[str, list[float]] = {"per chunk": [], "every step": []}
            for _ in range(args.repeat):
                for name in runs:
                    runs[name].append(await steps_per_s(worker, args.chunk, name == "every step", args.seconds, rng))
        finally:
            worker.close()
        per_chunk, every = statistics.median(runs["per chunk"]), statistics.median(runs["every step"])
        rows.append({"image_size": size, "per_chunk_steps_per_s": round(per_chunk, 1),
                     "every_step_steps_per_s": round(every, 1), "speedup": round(per_chunk / every, 2),
                     "runs": runs})
        print(f"{args.task} rgb {size}x{size}, K={args.chunk}: per chunk {per_chunk:6.1f} steps/s | "
              f"every step {every:6.1f} steps/s | {per_chunk / every:.2f}x", flush=True)
    return {"task": args.task, "chunk": args.chunk, "seconds": args.seconds, "repeat": args.repeat,
            "gl": os.environ.get("MUJOCO_GL", ""), "machine": platform.machine(), "cores": os.cpu_count(),
            "command": "python benchmarks/camera_obs.py " + " ".join(sys.argv[1:]), "rows": rows}


def main() -> None:
    p = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    p.add_argument("--task", default="Lift")
    p.add_argument("--sizes", type=int, nargs="+", default=[64, 84])
    p.add_argument("--chunk", type=int, default=8)
    p.add_argument("--seconds", type=float, default=5.0)
    p.add_argument("--repeat", type=int, default=2)
    p.add_argument("--out", default=str(RESULTS / "camera_obs.json"))
    args = p.parse_args()
    result = asyncio.run(measure(args))
    Path(args.out).parent.mkdir(parents=True, exist_ok=True)
    Path(args.out).write_text(json.dumps(result, indent=2) + "\n")
    print(f"written {args.out}")


if __name__ == "__main__":
    main()
