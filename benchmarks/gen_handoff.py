"""What one of gen's forward passes costs on the CPU, as its event loop waits for it.

    python benchmarks/gen_handoff.py                  # batch 4, 1500 passes per variant and load
    python benchmarks/gen_handoff.py --batch 16 --passes 3000

Two measurements, on the quickstart's policy (64x64 MLP, chunk 4) with Hopper's sizes (11 observations, 3
actions), one torch thread as gen has it:

* ``act``: the pass itself, back to back (the median of 5 rounds, the variants alternating). ``distributions`` is what ``GaussianChunkPolicy.sample`` did before:
  ``torch.distributions.Normal`` (built, its arguments checked) and one concatenated copy to numpy; ``act`` is
  the hand-written mean + std * eps, with the CPU tensors' own memory returned.
* ``handoff``: seconds from the event loop's request to the result in its hands, one pass every 0.5 ms, with
  ``--load`` other processes spinning on the cores (0 and 2 by default: an idle and a loaded 2-core machine).
  ``pool`` runs the pass on gen's forward thread (``ebrl.threads.TorchPool``, ``loop.run_in_executor``);
  ``inline`` runs it on the loop, which is what gen does on the CPU while passes are short
  (``ebrl/sched/forward.py``, ``Forward.inline``).

Results go to benchmarks/results/gen_handoff.json.
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

sys.path.insert(0, str(Path(__file__).resolve().parent.parent))

import numpy as np  # noqa: E402
import torch  # noqa: E402

from ebrl import bench, threads  # noqa: E402
from ebrl.config import PolicySection  # noqa: E402
from ebrl.envs.obs import ObsLayout  # noqa: E402
from ebrl.policies import make_policy  # noqa: E402

RESULTS = Path(__file__).resolve().parent / "results"


def policy() -> torch.nn.Module:
    model = make_policy(PolicySection(kind="mlp", chunk=4, hidden=[64, 64]), ObsLayout.vector(11), 3)
    return model.eval()


def with_distributions(model, obs: np.ndarray) -> tuple[np.ndarray, ...]:
    """The pass as it was: a checked ``Normal``, its rsample and log_prob, and one concatenated host copy."""
    with torch.no_grad():
        o = model.flat(obs)
        mean = model.actor(o)
        d = torch.distributions.Normal(mean, model.log_std.expand_as(mean).exp())
        v = model.critic(o).squeeze(-1)
        a = d.rsample()
        outs = (a.reshape(len(obs), model.chunk, model.action_dim), d.log_prob(a).sum(-1), v, a.new_zeros(len(obs), 0))
        widths = [int(np.prod(t.shape[1:])) for t in outs]
        flat = torch.cat([t.reshape(len(obs), w) for t, w in zip(outs, widths)], 1).cpu().numpy()
        return tuple(flat[:, sum(widths[:i]):sum(widths[:i + 1])] for i in range(len(outs)))


def per_pass_us(variants: dict, passes: int, rounds: int = 5) -> dict[str, float]:
    """Median over ``rounds`` (the variants alternating) of each variant's mean µs per pass, after a second of
    warm-up."""
    until = time.perf_counter() + 1.0
    while time.perf_counter() < until:
        for fn in variants.values():
            fn()
    times: dict[str, list[float]] = {name: [] for name in variants}
    for _ in range(rounds):
        for name, fn in variants.items():
            start = time.perf_counter()
            for _ in range(passes):
                fn()
            times[name].append((time.perf_counter() - start) / passes * 1e6)
    return {name: statistics.median(t) for name, t in times.items()}


def spin(stop) -> None:
    while not stop.is_set():
        pass


async def handoff(model, obs: np.ndarray, passes: int) -> dict[str, dict[str, float]]:
    pool, loop = threads.TorchPool("bench-forward"), asyncio.get_running_loop()
    seconds: dict[str, list[float]] = {"pool": [], "inline": []}
    for _ in range(2):  # each variant twice, alternating: drift hits both alike
        for name in seconds:
            for _ in range(passes // 2):
                start = time.perf_counter()
                if name == "pool":
                    await loop.run_in_executor(pool, model.act, obs)
                else:
                    model.act(obs)
                seconds[name].append(time.perf_counter() - start)
                await asyncio.sleep(0.0005)
    pool.shutdown()
    return {name: {"mean_us": statistics.fmean(s) * 1e6, "p50_us": float(np.percentile(s, 50) * 1e6),
                   "p99_us": float(np.percentile(s, 99) * 1e6)} for name, s in seconds.items()}


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    parser.add_argument("--batch", type=int, default=4)
    parser.add_argument("--passes", type=int, default=1500)
    parser.add_argument("--loads", default="0,2", help="spinning processes beside the loop, one run each")
    parser.add_argument("--json", default=str(RESULTS / "gen_handoff.json"))
    args = parser.parse_args()
    threads.set_threads(1)
    torch.manual_seed(0)
    model = policy()
    obs = np.random.default_rng(0).normal(size=(args.batch, 11)).astype(np.float32)
    act = per_pass_us({"distributions": lambda: with_distributions(model, obs), "act": lambda: model.act(obs)},
                      args.passes)
    print(f"act, batch {args.batch}: {act['distributions']:.0f} µs with torch.distributions, "
          f"{act['act']:.0f} µs written out ({act['distributions'] / act['act']:.2f}x)", flush=True)
    loads = []
    for load in [int(n) for n in args.loads.split(",")]:
        stop = mp.Event()
        spinners = [mp.Process(target=spin, args=(stop,), daemon=True) for _ in range(load)]
        for p in spinners:
            p.start()
        try:
            row = {"load": load, **asyncio.run(handoff(model, obs, args.passes))}
        finally:
            stop.set()
            for p in spinners:
                p.join()
        row["pool_over_inline_us"] = row["pool"]["mean_us"] - row["inline"]["mean_us"]
        loads.append(row)
        print(f"load {load}: loop waits {row['pool']['mean_us']:.0f} µs per pass through the forward thread, "
              f"{row['inline']['mean_us']:.0f} µs inline (p99 {row['pool']['p99_us']:.0f} / "
              f"{row['inline']['p99_us']:.0f})", flush=True)
    command = ("python benchmarks/gen_handoff.py " + " ".join(sys.argv[1:])).strip()
    machine = f"{platform.machine()}, {len(os.sched_getaffinity(0))} cores visible, torch {torch.__version__}"
    Path(args.json).write_text(json.dumps({"command": command, "commit": bench.commit(), "machine": machine,
                                           "batch": args.batch, "passes": args.passes, "act_us": act,
                                           "loads": loads}, indent=1) + "\n")
    print(f"wrote {args.json}")


if __name__ == "__main__":
    main()
