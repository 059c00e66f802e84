"""Training's rate: decisions per second through PPO updates of a config's policy, algorithm and batch size.

    python benchmarks/train_rate.py --configs configs/quickstart.toml --out results.json           # here, CPU
    python benchmarks/train_rate.py --configs configs/bench_w2_gpu.toml configs/bench_w3.toml     # on a GPU

What the train service spends per update, minus building the batch: ``PPO.update`` (the decoupled recompute
pass, ``algo.epochs`` x ``algo.minibatches`` gradient steps) on a batch of ``train.batch_size`` decisions of
made-up observations of the config's layout (the vision layout of benchmarks/gpu/forward.py for camera
configs), under the config's ``policy.dtype`` and, on a GPU, also bfloat16. Two ways of taking a step are
measured side by side in interleaved rounds:

- ``device``: as training runs since issue 35 -- a fused Adam that skips a non-finite step on the device
  (``found_inf``), the statistics added up there, the host reading the device once per epoch;
- ``host``: an unfused Adam whose every step the host checks (``bool(finite)``), one wait for the device per
  gradient step, as before (the code before issue 35 also read five statistics per step).

On the CPU there is nothing to wait for and the two differ only by the optimizer's kernel.
"""

from __future__ import annotations

import argparse
import json
import platform
import statistics
import sys
import time
from pathlib import Path

import numpy as np
import torch

ROOT = Path(__file__).resolve().parent.parent
sys.path.insert(0, str(ROOT))
sys.path.insert(0, str(ROOT / "benchmarks" / "gpu"))

from ebrl import config as config_mod, devices  # noqa: E402
from ebrl.algos.ppo import PPO, Batch  # noqa: E402
from ebrl.envs.obs import ObsLayout, sample_observations  # noqa: E402
from ebrl.policies import make_policy  # noqa: E402
from forward import LAYOUTS  # noqa: E402

STATE_DIMS = {"Lift": 42, "InvertedPendulum-v5": 4}  # observation sizes of the state configs measured here
ACTION_DIMS = {"Lift": 7, "InvertedPendulum-v5": 1}


def layout_of(cfg) -> tuple[ObsLayout, int]:
    """The observation layout and action size of a config's task, without building it."""
    if cfg.env.kwargs.get("obs") == "rgb":
        return LAYOUTS["vision"], 7
    return ObsLayout.vector(STATE_DIMS[cfg.env.id]), ACTION_DIMS[cfg.env.id]


def make_batch(model, layout: ObsLayout, n: int, device: torch.device, rng: np.random.Generator) -> Batch:
    obs = sample_observations(layout, n, rng)
    with torch.no_grad():
        actions, logprobs, values, latents = model.act(obs)
    f = {k: torch.as_tensor(v, device=device) for k, v in
         dict(obs=obs, actions=actions, latents=latents, logprobs=logprobs, values=values).items()}
    return Batch(**f, advantages=torch.randn(n, device=device), returns=torch.randn(n, device=device),
                 versions=np.zeros(n, np.int64))


def rate(ppo: PPO, batch: Batch, dtype: str, seconds: float, device: torch.device) -> float:
    """Decisions per second over whole updates (the last one finished: ``update`` reads its numbers back)."""
    with devices.autocast(device, dtype):
        ppo.update(batch)  # warm-up: kernels, the allocator, Adam's state
        done, start = 0, time.perf_counter()
        while time.perf_counter() - start < seconds or done == 0:
            ppo.update(batch)
            done += len(batch)
    return done / (time.perf_counter() - start)


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    parser.add_argument("--configs", nargs="+", default=["configs/quickstart.toml"])
    parser.add_argument("--device", default="auto")
    parser.add_argument("--seconds", type=float, default=3.0)
    parser.add_argument("--rounds", type=int, default=3)
    parser.add_argument("--out", default="train_rate.json")
    args = parser.parse_args()
    device = devices.resolve(args.device, "--device")
    rng, rows = np.random.default_rng(0), []
    for path in args.configs:
        cfg = config_mod.load(path)
        layout, action_dim = layout_of(cfg)
        dtypes = ["float32", "bfloat16"] if device.type == "cuda" else [cfg.policy.dtype]
        dtypes = [d for d in dtypes if d in ("float32", "bfloat16")] or ["float32"]
        torch.manual_seed(0)
        model = make_policy(cfg.policy, layout, action_dim).to(device)
        batch = make_batch(model, layout, cfg.train.batch_size, device, rng)
        start = {k: v.clone() for k, v in model.state_dict().items()}
        rates: dict[str, list[float]] = {f"{way}_{dtype}": [] for dtype in dtypes for way in ("host", "device")}
        for _ in range(args.rounds):
            for name in rates:
                way, dtype = name.split("_")
                model.load_state_dict(start)
                ppo = PPO(model, cfg.algo, cfg.train.lr)
                if way == "host":
                    ppo.optimizer = torch.optim.Adam(model.parameters(), lr=cfg.train.lr, eps=1e-5)
                rates[name].append(rate(ppo, batch, dtype, args.seconds, device))
        row = {"config": path, "batch_size": cfg.train.batch_size, "epochs": cfg.algo.epochs,
               "minibatches": cfg.algo.minibatches,
               "parameters": sum(p.numel() for p in model.parameters()),
               **{f"{k}_decisions_per_s": statistics.median(v) for k, v in rates.items()},
               **{f"device_over_host_{d}": statistics.median(rates[f"device_{d}"]) / statistics.median(rates[f"host_{d}"])
                  for d in dtypes}}
        rows.append(row)
        print(json.dumps(row), flush=True)
    out = {"command": " ".join(["python", "benchmarks/train_rate.py", *sys.argv[1:]]),
           "machine": {"torch": torch.__version__, "threads": torch.get_num_threads(), "platform": platform.platform(),
                       "device": devices.describe(device)},
           "rows": rows}
    Path(args.out).write_text(json.dumps(out, indent=1) + "\n")


if __name__ == "__main__":
    main()
