"""ManiSkill on GPU PhysX: what one chunk of a vectorized group costs, and what moving its data costs beside it.

    python benchmarks/gpu/maniskill_step.py --envs 128,256,512 --out /tmp/maniskill_step.json

For each group size and observation kind (``state``, and ``rgb64`` at 64 px), one :class:`ManiSkillBatch` of
PickCube-v1 on ``physx_cuda`` runs chunks of ``--chunk`` random actions through the same
:class:`~ebrl.envs.batch.BatchRunner` a sim group's process uses: the chunk's wall time (physics, rendering,
partial resets, the one copy to the host) and env steps/s. Beside it, on the same machine, the host-side costs
of the bytes path from benchmarks/vector_transfer.py (worker pipe, bus exchange, per-env bookkeeping). Their
ratio decides item 2 of the GPU-parallel simulation issue: where the bytes path is more than 10 % of the chunk,
sim and gen on one host should exchange CUDA memory handles instead of copies.
"""

from __future__ import annotations

import argparse
import asyncio
import json
import statistics
import sys
import time
from pathlib import Path

import numpy as np
import torch

ROOT = Path(__file__).resolve().parents[2]
sys.path[:0] = [str(ROOT), str(ROOT / "benchmarks")]

from ebrl.envs import EnvSpec  # noqa: E402
from ebrl.envs.batch import BatchRunner, ManiSkillBatch  # noqa: E402
import vector_transfer  # noqa: E402

KINDS = {"state": {"obs": "state"}, "rgb64": {"obs": "rgb", "image_size": 64}}


def chunk_ms(kind: str, n: int, k: int, repeat: int) -> tuple[float, int]:
    spec = EnvSpec("PickCube-v1", backend="maniskill", max_episode_steps=50,
                   kwargs={**KINDS[kind], "sim_backend": "physx_cuda", "control_mode": "pd_joint_delta_pos"})
    batch = ManiSkillBatch(spec, n, seed=0)
    try:
        runner = BatchRunner(batch)
        obs = runner.reset(np.zeros(n, np.int64))
        rng = np.random.default_rng(0)
        times = []
        for i in range(repeat + 3):
            actions = rng.uniform(-1, 1, (n, k, 8)).astype(np.float32)
            torch.cuda.synchronize()
            t0 = time.perf_counter()
            runner.chunk(actions)  # ends with the copy to the host: synchronised
            if i >= 3:
                times.append(time.perf_counter() - t0)
        return statistics.median(times) * 1e3, int(obs.shape[1])
    finally:
        batch.close()


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    parser.add_argument("--envs", default="128,256,512")
    parser.add_argument("--chunk", type=int, default=4)
    parser.add_argument("--repeat", type=int, default=20)
    parser.add_argument("--kinds", default="state,rgb64")
    parser.add_argument("--out", required=True)
    args = parser.parse_args()
    rows = []
    for kind in args.kinds.split(","):
        for n in (int(x) for x in args.envs.split(",")):
            try:
                ms, dim = chunk_ms(kind, n, args.chunk, args.repeat)
            except Exception as exc:  # noqa: BLE001  e.g. out of GPU memory at a large rgb batch: say so, go on
                print(f"{kind} {n}: {type(exc).__name__}: {exc}", flush=True)
                rows.append({"kind": kind, "envs": n, "error": f"{type(exc).__name__}: {exc}"})
                continue
            ended = max(1, n // 12)
            pipe = vector_transfer.pipe_ms(n, dim, ended, 10)
            book = vector_transfer.bookkeeping_ms(n, dim, args.chunk, ended, 10)
            exchange, size = asyncio.run(vector_transfer.exchange_ms(n, dim, args.chunk, 10))
            moving = pipe + exchange + book
            row = {"kind": kind, "envs": n, "obs_values": dim, "chunk_ms": round(ms, 2),
                   "env_steps_per_s": round(n * args.chunk / ms * 1e3), "pipe_ms": round(pipe, 2),
                   "exchange_ms": round(exchange, 2), "bookkeeping_ms": round(book, 2), "obs_bytes": size,
                   "bytes_path_share": round((pipe + exchange) / ms, 3), "host_share": round(moving / ms, 3)}
            rows.append(row)
            print(json.dumps(row), flush=True)
    out = {"command": " ".join(sys.argv), "gpu": torch.cuda.get_device_name(0), "chunk": args.chunk,
           "date": time.strftime("%Y-%m-%d"), "rows": rows}
    Path(args.out).write_text(json.dumps(out, indent=2) + "\n")


if __name__ == "__main__":
    main()
