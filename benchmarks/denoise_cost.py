"""Generation cost per action chunk vs denoising steps N of the flow policy (mlp and cnn as N-free references).

    python benchmarks/denoise_cost.py                       # ~1 min on one core
    python benchmarks/denoise_cost.py --steps 1 4 16 --batches 1 --seconds 0.5

Two observation layouts: ``state`` (robosuite Lift's 42-dim state) and
``vision`` (a 3x64x64 camera image + 9 proprioception values + a 16-token
instruction). Action dimension 7, chunk K = 8, hidden [64, 64], the config's
default conv channels and embedding width. Each measurement is the policy's
``act`` (what the generation service calls: forward pass, sampling, numpy out)
at one batch size with one torch thread: warm-up calls, then timed calls for
``--seconds``. The variants of one layout and batch size are measured in
``--rounds`` interleaved rounds; the median over rounds is reported, with the
ratio to the flow policy at N = 1.

Results go to benchmarks/results/denoise_cost.json.
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

sys.path.insert(0, str(Path(__file__).resolve().parent.parent))

from ebrl.config import PolicySection  # noqa: E402
from ebrl.envs.obs import ObsField, ObsLayout, sample_observations  # noqa: E402
from ebrl.policies import make_policy  # noqa: E402

RESULTS = Path(__file__).resolve().parent / "results"
ACTION_DIM, CHUNK, HIDDEN = 7, 8, [64, 64]
LAYOUTS = {
    "state": ObsLayout.vector(42),
    "vision": ObsLayout((ObsField("image", "image", (3, 64, 64)), ObsField("proprio", "vector", (9,)),
                         ObsField("instruction", "tokens", (16,)))),
}
REFERENCE = {"state": "mlp", "vision": "cnn"}  # the Gaussian policy of each layout


def median_ms(model: torch.nn.Module, obs: np.ndarray, warmup: int, seconds: float) -> tuple[float, int]:
    """Median wall time of one ``act`` call in milliseconds, and how many calls were timed."""
    for _ in range(warmup):
        model.act(obs)
    times: list[float] = []
    deadline = time.perf_counter() + seconds
    while len(times) < 5 or time.perf_counter() < deadline:
        start = time.perf_counter()
        model.act(obs)
        times.append(time.perf_counter() - start)
    return 1e3 * statistics.median(times), len(times)


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    parser.add_argument("--steps", type=int, nargs="+", default=[1, 2, 4, 8, 16], help="flow denoising steps N")
    parser.add_argument("--batches", type=int, nargs="+", default=[1, 16], help="observations per forward pass")
    parser.add_argument("--seconds", type=float, default=0.4, help="timed seconds per measurement")
    parser.add_argument("--rounds", type=int, default=3,
                        help="rounds over all variants of a layout and batch (order rotating); the median is reported")
    parser.add_argument("--warmup", type=int, default=5, help="untimed calls before each measurement")
    parser.add_argument("--out", default=str(RESULTS / "denoise_cost.json"))
    args = parser.parse_args()
    torch.set_num_threads(1)

    rows = []
    print(f"{'layout':7s} {'batch':>5s} {'policy':9s} {'ms/act':>8s} {'ms/chunk':>9s} {'x N=1':>10s} {'calls':>6s}")
    for layout_name, layout in LAYOUTS.items():
        for batch in args.batches:
            obs = sample_observations(layout, batch)
            variants = [(REFERENCE[layout_name], None)] + [("flow", n) for n in args.steps]
            base = None
            models = []
            for kind, steps in variants:
                torch.manual_seed(0)
                cfg = PolicySection(kind=kind, chunk=CHUNK, hidden=HIDDEN, denoise_steps=steps or 1)
                models.append(make_policy(cfg, layout, ACTION_DIM))
            runs: list[list[float]] = [[] for _ in variants]
            calls = [0] * len(variants)
            for r in range(args.rounds):  # interleaved, so that drifting machine load hits every variant alike
                for i in [(r + j) % len(variants) for j in range(len(variants))]:
                    ms, n = median_ms(models[i], obs, args.warmup, args.seconds)
                    runs[i].append(ms)
                    calls[i] += n
            for (kind, steps), times, n in zip(variants, runs, calls):
                ms = statistics.median(times)
                if kind == "flow" and steps == 1:
                    base = ms
                rows.append({"layout": layout_name, "batch": batch, "policy": kind, "denoise_steps": steps,
                             "median_ms_per_act": ms, "median_ms_per_chunk": ms / batch, "timed_calls": n,
                             "round_medians_ms": times})
            for row in rows[-len(variants):]:
                row["ratio_to_flow_n1"] = row["median_ms_per_act"] / base if base else None
                name = row["policy"] + (f" N={row['denoise_steps']}" if row["denoise_steps"] else "")
                ratio = f"{row['ratio_to_flow_n1']:.2f}" if base else "-"
                print(f"{layout_name:7s} {batch:5d} {name:9s} {row['median_ms_per_act']:8.3f} "
                      f"{row['median_ms_per_chunk']:9.3f} {ratio:>10s} {row['timed_calls']:6d}", flush=True)

    result = {
        "command": "python benchmarks/denoise_cost.py " + " ".join(sys.argv[1:]),
        "machine": f"{platform.machine()}, {os.cpu_count()} cores visible, torch {torch.__version__}, 1 thread",
        "action_dim": ACTION_DIM, "chunk": CHUNK, "hidden": HIDDEN,
        "layouts": {name: layout.describe() for name, layout in LAYOUTS.items()},
        "seconds_per_measurement": args.seconds, "rounds": args.rounds, "warmup_calls": args.warmup,
        "rows": rows,
    }
    path = Path(args.out)
    path.parent.mkdir(parents=True, exist_ok=True)
    path.write_text(json.dumps(result, indent=2) + "\n")
    print(f"wrote {path}")


if __name__ == "__main__":
    main()
