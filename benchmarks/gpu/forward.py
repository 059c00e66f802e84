"""Generation's forward pass on the CPU and on the GPU, side by side: action chunks per second of ``act``.

    python benchmarks/gpu/forward.py --out results.json          # on the lent GPU machine (check.sh runs it)

What the generation service calls per batch: observations staged in (pinned, non-blocking on a GPU), the
policy's ``act`` (encoder, N denoising steps of the flow policy, sampling), results back in one transfer.
Policies: the mlp (the quickstart's) and the flow policy at N = 10 with hidden [256, 256] on a camera
layout (3x64x64 image + 9 proprio + instruction tokens), batch sizes 8 to 512. Each (policy, batch) pair is
measured on every device (on the GPU in float32 and with bfloat16 autocast, ``policy.dtype``, each eagerly and
through CUDA graphs, ``gen.compile``) in interleaved rounds; the median over rounds is reported with the
GPU/CPU, bfloat16/float32 and graphs/eager ratios. W3 (the 306M flow transformer) is measured at 16 and 64.
The CPU side uses every core this process may run on (the GPU machine has 16).
"""

from __future__ import annotations

import argparse
import json
import os
import platform
import statistics
import sys
import time
from pathlib import Path

import numpy as np
import torch

sys.path.insert(0, str(Path(__file__).resolve().parent.parent.parent))

from ebrl import devices  # noqa: E402
from ebrl.config import PolicySection  # noqa: E402
from ebrl.envs.obs import ObsField, ObsLayout, sample_observations  # noqa: E402
from ebrl.policies import make_policy  # noqa: E402
from ebrl.policies.graphs import Actor  # noqa: E402

ACTION_DIM, CHUNK = 7, 8
LAYOUTS = {"state": ObsLayout.vector(42),
           "vision": ObsLayout((ObsField("image", "image", (3, 64, 64)), ObsField("proprio", "vector", (9,)),
                                ObsField("instruction", "tokens", (16,))))}
POLICIES = {"mlp-state": ("state", dict(kind="mlp", hidden=[64, 64])),
            "flow10-vision": ("vision", dict(kind="flow", hidden=[256, 256], denoise_steps=10)),
            # W3 (configs/bench_w3.toml): the flow head on a 306M-parameter transformer backbone
            "flow10-w3": ("vision", dict(kind="flow", backbone="transformer", width=1024, depth=24, heads=16,
                                         patch=8, hidden=[1024, 1024], denoise_steps=10))}
BATCHES = {"flow10-w3": [16, 64]}  # the W3 batch (4 groups of 4) and a larger one
CPU_MAX = {"flow10-w3": 16}  # W3 on the CPU: one batch of 16 takes a second; larger ones are not measured


def chunks_per_s(actor: Actor, stage, obs: np.ndarray, seconds: float) -> float:
    for _ in range(3):  # warm-up (CUDA context, kernels, the allocator, a graph's capture)
        actor(stage(obs))
    done, start = 0, time.perf_counter()
    while time.perf_counter() - start < seconds:
        actor(stage(obs))  # returns numpy: the GPU work is finished when it returns
        done += len(obs)
    return done / (time.perf_counter() - start)


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    parser.add_argument("--batches", type=int, nargs="+", default=[8, 64, 512])
    parser.add_argument("--seconds", type=float, default=1.0)
    parser.add_argument("--rounds", type=int, default=3)
    parser.add_argument("--out", default="gpu_forward.json")
    args = parser.parse_args()
    torch.set_num_threads(len(os.sched_getaffinity(0)))
    cuda = torch.cuda.is_available()
    # (device, policy.dtype, gen.compile)
    targets = [("cpu", "float32", "off")] + ([("cuda:0", t, c) for c in ("off", "cudagraphs")
                                               for t in ("float32", "bfloat16")] if cuda else [])
    rng = np.random.default_rng(0)
    rows = []
    for name, (layout_name, kwargs) in POLICIES.items():
        layout = LAYOUTS[layout_name]
        cfg = PolicySection(chunk=CHUNK, **kwargs)
        models = {d: make_policy(cfg, layout, ACTION_DIM).to(d).eval() for d in {d for d, _, _ in targets}}
        for batch in BATCHES.get(name, args.batches):
            obs = sample_observations(layout, batch, rng)
            here = [x for x in targets if not (x[0] == "cpu" and batch > CPU_MAX.get(name, batch))]
            actors = {x: Actor(models[x[0]], x[2], x[1]) for x in here}
            rates: dict[str, list[float]] = {"_".join(x): [] for x in here}
            for _ in range(args.rounds):
                for x in here:
                    stage = devices.Staging(torch.device(x[0]))
                    rates["_".join(x)].append(chunks_per_s(actors[x], stage, obs, args.seconds))
            row = {"policy": name, "batch": batch, **{f"{k}_chunks_per_s": statistics.median(r) for k, r in rates.items()}}
            if cuda:
                eager = row["cuda:0_float32_off_chunks_per_s"]
                if "cpu_float32_off_chunks_per_s" in row:
                    row["gpu_over_cpu"] = eager / row["cpu_float32_off_chunks_per_s"]
                row["bf16_over_fp32"] = row["cuda:0_bfloat16_off_chunks_per_s"] / eager
                row["graphs_over_eager"] = row["cuda:0_float32_cudagraphs_chunks_per_s"] / eager
                row["graphs_over_eager_bf16"] = (row["cuda:0_bfloat16_cudagraphs_chunks_per_s"]
                                                 / row["cuda:0_bfloat16_off_chunks_per_s"])
            rows.append(row)
            print(json.dumps(row), flush=True)
    out = {"command": " ".join(["python", "benchmarks/gpu/forward.py", *sys.argv[1:]]),
           "machine": {"cpu_threads": torch.get_num_threads(), "platform": platform.platform(),
                       "torch": torch.__version__,
                       "gpu": devices.describe(torch.device("cuda", 0)) if cuda else None},
           "rows": rows}
    Path(args.out).write_text(json.dumps(out, indent=1) + "\n")


if __name__ == "__main__":
    main()
