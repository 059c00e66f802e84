"""GPU shares that bite: generation and training of W3 sharing one GPU under MPS at 30/70 and 50/50, against
each alone and both without MPS (time-slicing), side by side in one command.

    python benchmarks/gpu/mps_shares.py --seconds 10 --out mps_shares.json     # on a GPU machine (check.sh)

Each stage is a process of its own, as in a run: "gen" samples chunks from the W3 policy (the 306M flow
transformer of configs/bench_w3.toml, batch --gen-batch, 10 denoising steps), "train" does PPO-shaped
updates of the same policy (log-prob, entropy and value of a minibatch with gradients through the whole
chain, Adam). A share is what ``ebrl up`` gives a stage under an MPS plan: CUDA_MPS_ACTIVE_THREAD_PERCENTAGE
at launch, with the MPS control daemon started here (ebrl.resources.mps, as the launcher does) and quit at the
end. Both processes of a case warm up, then run the same window of wall-clock time. Reported per case: gen
chunks/s and train samples/s, and each as a fraction of that stage alone on the whole GPU.
"""

from __future__ import annotations

import argparse
import json
import os
import subprocess
import sys
import tempfile
import time
from pathlib import Path

ROOT = Path(__file__).resolve().parent.parent.parent
sys.path.insert(0, str(ROOT))

# (case, {stage: sm percent or None for no share}, with the MPS daemon)
CASES = [
    ("gen alone", {"gen": None}, False),
    ("train alone", {"train": None}, False),
    ("both, no MPS", {"gen": None, "train": None}, False),
    ("gen alone at 30%", {"gen": 30}, True),
    ("train alone at 30%", {"train": 30}, True),
    ("both at 30/70", {"gen": 30, "train": 70}, True),
    ("both at 50/50", {"gen": 50, "train": 50}, True),
]


def policy(device):
    import torch

    from ebrl import config
    from ebrl.envs.obs import ObsField, ObsLayout
    from ebrl.policies import make_policy
    cfg = config.load(str(ROOT / "configs/bench_w3.toml"))
    layout = ObsLayout((ObsField("image", "image", (3, 64, 64)), ObsField("proprio", "vector", (43,)),
                        ObsField("instruction", "tokens", (16,))))
    torch.manual_seed(0)
    with torch.device(device):
        return make_policy(cfg.policy, layout, 7), cfg


def worker(stage: str, start_at: float, seconds: float, gen_batch: int, train_batch: int) -> None:
    import numpy as np
    import torch
    device = torch.device("cuda", 0)
    model, cfg = policy(device)
    rng = np.random.default_rng(0)
    obs = np.concatenate([rng.uniform(0, 1, (train_batch, 3 * 64 * 64)), rng.normal(size=(train_batch, 43)),
                          rng.integers(1, 50, (train_batch, 16))], 1).astype(np.float32)
    if stage == "gen":
        model.eval()
        batch = obs[:gen_batch]
        step = lambda: model.act(batch)  # noqa: E731  (returns numpy: the GPU work is done)
        per_step = gen_batch
    else:
        opt = torch.optim.Adam(model.parameters(), lr=1e-5)
        o = torch.as_tensor(obs, device=device)
        actions = torch.randn(train_batch, cfg.policy.chunk, 7, device=device)
        latents = torch.randn(train_batch, cfg.policy.chunk, 7, device=device)

        def step() -> None:
            logp, entropy, value = model.evaluate(o, actions, latents)
            loss = -(logp.mean() + 0.01 * entropy.mean()) + value.pow(2).mean()
            opt.zero_grad(set_to_none=True)
            loss.backward()
            opt.step()
            torch.cuda.synchronize()
        per_step = train_batch
    for _ in range(3):
        step()
    while time.time() < start_at:  # both stages of a case measure the same window
        step()
    done, t0 = 0, time.time()
    while time.time() - t0 < seconds:
        step()
        done += per_step
    print(json.dumps({"stage": stage, "rate": done / (time.time() - t0)}), flush=True)


def run_case(stages: dict, env: dict, seconds: float, args) -> dict:
    start_at = time.time() + args.warmup
    procs = {}
    for stage, share in stages.items():
        e = dict(env)
        if share is not None:
            e["CUDA_MPS_ACTIVE_THREAD_PERCENTAGE"] = str(share)
        procs[stage] = subprocess.Popen(
            [sys.executable, __file__, "--worker", stage, "--start-at", str(start_at), "--seconds", str(seconds),
             "--gen-batch", str(args.gen_batch), "--train-batch", str(args.train_batch)],
            env=e, stdout=subprocess.PIPE, stderr=subprocess.PIPE, text=True)
    rates = {}
    for stage, p in procs.items():
        out, err = p.communicate(timeout=args.warmup + seconds + 120)
        if p.returncode != 0:
            raise RuntimeError(f"{stage} worker failed ({p.returncode}): {err[-2000:]}")
        rates[stage] = json.loads(out.strip().splitlines()[-1])["rate"]
    return rates


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    parser.add_argument("--seconds", type=float, default=10.0, help="measured window per case")
    parser.add_argument("--warmup", type=float, default=12.0, help="seconds from launch to the window's start")
    parser.add_argument("--gen-batch", type=int, default=16, help="envs per forward pass (W3: 4 groups of 4)")
    parser.add_argument("--train-batch", type=int, default=64, help="minibatch of an update (W3: 256 / 4)")
    parser.add_argument("--out", default="mps_shares.json")
    parser.add_argument("--worker", choices=("gen", "train"), help=argparse.SUPPRESS)
    parser.add_argument("--start-at", type=float, help=argparse.SUPPRESS)
    args = parser.parse_args()
    if args.worker:
        worker(args.worker, args.start_at, args.seconds, args.gen_batch, args.train_batch)
        return
    from ebrl.resources.mps import MpsDaemon
    from ebrl.resources.pool import mps_reachable
    if mps_reachable(os.environ.get("CUDA_MPS_PIPE_DIRECTORY", "/tmp/nvidia-mps")):
        sys.exit("an MPS daemon is already running: the cases without MPS would connect to it; quit it first")
    rows, alone = [], {}
    with tempfile.TemporaryDirectory() as logs:
        daemon = None
        try:
            for name, stages, mps in CASES:
                if mps and daemon is None:
                    daemon = MpsDaemon.ensure(logs)
                env = daemon.env if mps else dict(os.environ)
                rates = run_case(stages, env, args.seconds, args)
                for stage, rate in rates.items():
                    if len(stages) == 1 and stages[stage] is None:
                        alone[stage] = rate
                row = {"case": name, "mps": mps, "shares": stages, **{f"{s}_rate": r for s, r in rates.items()},
                       **{f"{s}_of_alone": r / alone[s] for s, r in rates.items() if s in alone}}
                rows.append(row)
                print(json.dumps(row), flush=True)
        finally:
            if daemon is not None:
                daemon.quit()
    out = {"command": " ".join(["python", "benchmarks/gpu/mps_shares.py", *sys.argv[1:]]),
           "units": {"gen_rate": "chunks/s", "train_rate": "samples/s (forward + backward + Adam)"},
           "rows": rows}
    Path(args.out).write_text(json.dumps(out, indent=1) + "\n")
    print(f"{'case':<22} {'gen chunks/s':>13} {'of alone':>9} {'train samples/s':>16} {'of alone':>9}")
    for r in rows:
        g, t = r.get("gen_rate"), r.get("train_rate")
        print(f"{r['case']:<22} {g or 0:>13.1f} {r.get('gen_of_alone', 0):>9.2f} {t or 0:>16.1f} "
              f"{r.get('train_of_alone', 0):>9.2f}")


if __name__ == "__main__":
    main()
