"""MuJoCo Warp: what one chunk of an mjwarp group costs at each group size, with and without Warp graphs.

    python benchmarks/gpu/mjwarp_step.py --worlds 1024,2048,4096 --out /tmp/mjwarp_step.json
    python benchmarks/gpu/mjwarp_step.py --device cpu --worlds 8 --repeat 3      # a try on Warp's CPU device

For each group size, one :class:`~ebrl.envs.batch.MjWarpBatch` of PandaPickCube-v0 runs chunks of ``--chunk``
random actions through the :class:`~ebrl.envs.batch.BatchRunner` a sim group's process uses: the chunk's wall
time (physics, the task's functions, partial resets at the chunk's end, the one copy to the host) and env
steps/s, with each env step's physics and each reset as Warp graphs (the default: CUDA graphs on the GPU, Warp's
CPU replay on the CPU) and launched eagerly. The first chunks
(kernel loading, graph capture) are left out. Prints and writes JSON rows.
"""

from __future__ import annotations

import argparse
import json
import statistics
import sys
import time
from pathlib import Path

import numpy as np
import torch

ROOT = Path(__file__).resolve().parents[2]
sys.path.insert(0, str(ROOT))

from ebrl.bench import commit  # noqa: E402
from ebrl.envs import EnvSpec  # noqa: E402
from ebrl.envs.batch import BatchRunner, MjWarpBatch  # noqa: E402


def measure(n: int, k: int, repeat: int, device: str, graph: bool) -> dict:
    spec = EnvSpec("PandaPickCube-v0", backend="mjwarp", kwargs={"device": device, "cuda_graph": graph})
    t0 = time.perf_counter()
    batch = MjWarpBatch(spec, list(range(n)))
    build_s = time.perf_counter() - t0
    runner = BatchRunner(batch)
    runner.reset(np.zeros(n, np.int64))
    rng = np.random.default_rng(0)
    times = []
    for i in range(repeat + 2):
        actions = rng.uniform(-1, 1, (n, k, batch.task.action_size)).astype(np.float32)
        t0 = time.perf_counter()
        runner.chunk(actions)  # ends with the copy to the host: synchronised
        if i >= 2:
            times.append(time.perf_counter() - t0)
    ms = 1000 * statistics.median(times)
    graphed = batch.graphed  # captured (where capture failed: eager, warned)
    batch.close()
    return {"worlds": n, "chunk": k, "device": str(batch.device), "cuda_graph": graphed,
            "build_s": round(build_s, 2), "chunk_ms_median": round(ms, 3),
            "env_steps_per_s": round(n * k / (ms / 1000)), "chunks": len(times)}


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    parser.add_argument("--worlds", default="1024,2048,4096")
    parser.add_argument("--chunk", type=int, default=4)
    parser.add_argument("--repeat", type=int, default=20)
    parser.add_argument("--device", default="cuda")
    parser.add_argument("--out", type=Path)
    args = parser.parse_args()
    rows = []
    for n in (int(w) for w in args.worlds.split(",")):
        for graph in (True, False):  # Warp graphs on the GPU and, Warp >= 1.13, on the CPU
            rows.append(measure(n, args.chunk, args.repeat, args.device, graph))
            print(json.dumps(rows[-1]), flush=True)
    out = {"command": " ".join(["python benchmarks/gpu/mjwarp_step.py", *sys.argv[1:]]), "commit": commit(),
           "device": torch.cuda.get_device_name(0) if torch.cuda.is_available() else "cpu", "rows": rows}
    if args.out:
        args.out.write_text(json.dumps(out, indent=1) + "\n")


if __name__ == "__main__":
    main()
