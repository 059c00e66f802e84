"""The VLA policy's generation and training rates beside W3's flow transformer, at the same batch sizes.

    python benchmarks/vla_rates.py --train-batch 8 --rounds 1 \\
        --out benchmarks/results/vla_rates_cpu.json                     # here: 2 CPU cores, 77 s
    python benchmarks/vla_rates.py --device cuda --dtype bfloat16 \\
        --policies vla-tiny vla-tiny-tokens vla-base w3 --out vla_rates_gpu.json       # the GPU kit (check.sh vla)

Policies (each with W3's chunk, denoising steps and action size, on the camera layout W3's benchmarks use:
a 3x64x64 image, 9 proprioception values, 16 instruction tokens; ``benchmarks/gpu/forward.py``):

- ``vla-tiny``: ``policy.kind = "vla"`` with the tests' backbones (a 2-layer SigLIP vision tower 32 wide at
  32 px, a 2-layer Llama decoder 32 wide), LoRA r = 4, head [64, 64]: what the machinery costs around a model
  that costs nothing;
- ``vla-tiny-tokens``: the same with the discrete action tokens head (``policy.options.head = "tokens"``: 256
  bins, K x A = 56 query tokens more in the sequence);
- ``vla-base``: a SigLIP-B/16-shaped tower (768 wide, 12 layers, 224 px: 196 patches) and a 16-layer Llama
  1024 wide (4 key-value heads), LoRA r = 16, head [1024, 1024]: W3's order of size (GPU);
- ``w3``: configs/bench_w3.toml's policy (the 306M-parameter flow transformer).

Generation: forwards per second of what the gen service calls per batch (``ebrl.policies.graphs.Actor``:
observations staged in, ``act``, results back), at ``--gen-batches`` (default bench_w3's: one group of 4, all 4
groups), under ``--dtype`` and, on a GPU, ``--compile`` (default CUDA graphs: ``captured`` says whether the
capture held). Training: PPO updates per second (``PPO.update``: ``epochs`` x ``minibatches`` gradient steps
on ``--train-batch`` decisions of made-up observations; benchmarks/train_rate.py's batch), with the
optimizer over the trainable parameters only. Each number is the median of ``--rounds`` interleaved rounds,
with ``--threads`` torch threads (1, as the services run by default). On the CPU W3 is slow (seconds a forward,
tens of seconds an update): the CPU record trains on batches of 8 (W3's epochs and minibatches, minibatches of
2) and takes one round, a warm-up call that outlasts ``--seconds`` counting as the measurement.
"""

from __future__ import annotations

import argparse
import dataclasses
import json
import os
import platform
import statistics
import sys
import time
from pathlib import Path

import numpy as np
import torch

ROOT = Path(__file__).resolve().parent.parent
sys.path.insert(0, str(ROOT))
sys.path.insert(0, str(ROOT / "benchmarks"))
sys.path.insert(0, str(ROOT / "benchmarks" / "gpu"))

from ebrl import config as config_mod, devices  # noqa: E402
from ebrl.algos.ppo import PPO  # noqa: E402
from ebrl.envs.obs import sample_observations  # noqa: E402
from ebrl.policies import make_policy  # noqa: E402
from ebrl.policies.graphs import Actor  # noqa: E402
from train_rate import layout_of, make_batch  # noqa: E402

W3 = ROOT / "configs" / "bench_w3.toml"
TINY = {"vision_config": {"model_type": "siglip_vision_model", "hidden_size": 32, "intermediate_size": 64,
                          "num_hidden_layers": 2, "num_attention_heads": 2, "image_size": 32, "patch_size": 8},
        "language_config": {"model_type": "llama", "vocab_size": 4096, "hidden_size": 32, "intermediate_size": 64,
                            "num_hidden_layers": 2, "num_attention_heads": 2, "num_key_value_heads": 1},
        "lora": {"r": 4}}
BASE = {"vision_config": {"model_type": "siglip_vision_model", "hidden_size": 768, "intermediate_size": 3072,
                          "num_hidden_layers": 12, "num_attention_heads": 12, "image_size": 224, "patch_size": 16},
        "language_config": {"model_type": "llama", "vocab_size": 32000, "hidden_size": 1024,
                            "intermediate_size": 2816, "num_hidden_layers": 16, "num_attention_heads": 16,
                            "num_key_value_heads": 4},
        "lora": {"r": 16}}
VLAS = {"vla-tiny": (TINY, [64, 64]), "vla-tiny-tokens": ({**TINY, "head": "tokens"}, [64, 64]),
        "vla-base": (BASE, [1024, 1024])}
BOUNDS = (np.full(7, -1.0), np.full(7, 1.0))  # robosuite Lift's OSC actions


def build(name: str, w3: config_mod.Config, layout, action_dim: int, device: torch.device) -> torch.nn.Module:
    """Policy ``name`` with W3's chunk and denoising steps (module docstring), on ``device``."""
    torch.manual_seed(0)
    if name == "w3":
        return make_policy(w3.policy, layout, action_dim).to(device)
    from ebrl.policies.vla import VLAPolicy

    options, hidden = VLAS[name]
    cfg = dataclasses.replace(w3.policy, hidden=hidden)
    cfg.options = options  # (PolicySection.options once policy kinds are a registry: the same table)
    return VLAPolicy.from_config(cfg, layout, action_dim, BOUNDS).to(device)


def per_s(call, seconds: float, warmups: int) -> float:
    """Calls of ``call`` per second over at least ``seconds`` (at least one call) after ``warmups`` calls; where
    one warm-up call alone outlasts ``seconds`` (W3 on a CPU: several seconds a forward), it is the measurement."""
    for _ in range(warmups):  # kernels, the allocator, Adam's state, a graph's capture
        start = time.perf_counter()
        call()
        took = time.perf_counter() - start
        if took >= seconds and warmups == 1:
            return 1.0 / took
    done, start = 0, time.perf_counter()
    while time.perf_counter() - start < seconds or done == 0:
        call()  # returns numpy, or update's statistics: the device's work is finished
        done += 1
    return done / (time.perf_counter() - start)


def forwards_per_s(actor: Actor, stage, obs: np.ndarray, seconds: float) -> float:
    return per_s(lambda: actor(stage(obs)), seconds, 2 if actor.device.type == "cuda" else 1)


def updates_per_s(ppo: PPO, batch, dtype: str, seconds: float, device: torch.device) -> float:
    with devices.autocast(device, dtype):
        return per_s(lambda: ppo.update(batch), seconds, 2 if device.type == "cuda" else 1)


def measure(name: str, model, layout, args, algo, device: torch.device) -> dict:
    """One policy's row: parameters, generation's forwards/s per batch size, training's updates/s."""
    rng = np.random.default_rng(0)
    compile_ = args.compile if device.type == "cuda" else "off"
    actors = {b: Actor(model, compile_, args.dtype) for b in args.gen_batches}
    observations = {b: sample_observations(layout, b, rng) for b in args.gen_batches}
    batch = make_batch(model, layout, args.train_batch, device, rng)
    start = {k: v.clone() for k, v in model.state_dict().items()}
    gen: dict[int, list[float]] = {b: [] for b in args.gen_batches}
    train: list[float] = []
    stage = devices.Staging(device)
    for _ in range(args.rounds):
        for b in args.gen_batches:
            gen[b].append(forwards_per_s(actors[b], stage, observations[b], args.seconds))
        model.load_state_dict(start)
        ppo = PPO(model, algo, 1e-5)  # the learner's optimizer: trainable parameters only
        train.append(updates_per_s(ppo, batch, args.dtype, args.seconds, device))
    trainable = sum(p.numel() for p in model.parameters() if p.requires_grad)
    row = {"policy": name, "kind": model.kind, "parameters": sum(p.numel() for p in model.parameters()),
           "trainable": trainable,
           "gen": {str(b): {"forwards_per_s": statistics.median(r), "chunks_per_s": b * statistics.median(r),
                            "captured": bool(actors[b].graphed)} for b, r in gen.items()},
           "train": {"batch": args.train_batch, "epochs": algo.epochs, "minibatches": algo.minibatches,
                     "updates_per_s": statistics.median(train),
                     "decisions_per_s": args.train_batch * statistics.median(train)}}
    print(json.dumps(row), flush=True)
    return row


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    parser.add_argument("--policies", nargs="+", default=["vla-tiny", "vla-tiny-tokens", "w3"], choices=[*VLAS, "w3"])
    parser.add_argument("--device", default="cpu")
    parser.add_argument("--dtype", default="float32", choices=["float32", "bfloat16"])
    parser.add_argument("--compile", default="cudagraphs", choices=["off", "cudagraphs"], help="on a GPU")
    parser.add_argument("--gen-batches", type=int, nargs="+", default=[4, 16])
    parser.add_argument("--train-batch", type=int, default=0, help="default: bench_w3's train.batch_size (256)")
    parser.add_argument("--epochs", type=int, default=0, help="default: bench_w3's algo.epochs (2)")
    parser.add_argument("--minibatches", type=int, default=0, help="default: bench_w3's algo.minibatches (4)")
    parser.add_argument("--seconds", type=float, default=1.0, help="each measurement, at least one call")
    parser.add_argument("--rounds", type=int, default=3)
    parser.add_argument("--threads", type=int, default=1,
                        help="torch threads (1: what generation and training take by default, gen.threads and "
                             "train.threads); 0: torch's default")
    parser.add_argument("--out", default="vla_rates.json")
    args = parser.parse_args()
    if args.threads:
        torch.set_num_threads(args.threads)
    device = devices.resolve(args.device, "--device")
    w3 = config_mod.load(str(W3))
    algo = dataclasses.replace(w3.algo, epochs=args.epochs or w3.algo.epochs,
                               minibatches=args.minibatches or w3.algo.minibatches)
    args.train_batch = args.train_batch or w3.train.batch_size
    layout, action_dim = layout_of(w3)
    rows, load = [], os.getloadavg()[0]
    for name in args.policies:
        started = time.perf_counter()
        model = build(name, w3, layout, action_dim, device)
        row = measure(name, model, layout, args, algo, device)
        row["wall_s"] = round(time.perf_counter() - started, 1)
        rows.append(row)
        del model
    out = {"command": " ".join(["python", "benchmarks/vla_rates.py", *sys.argv[1:]]),
           "machine": {"torch": torch.__version__, "threads": torch.get_num_threads(), "platform": platform.platform(),
                       "device": devices.describe(device), "dtype": args.dtype,
                       # other work on the host while it ran: the 1-minute load average at the start and the end
                       "load_average": [round(load, 2), round(os.getloadavg()[0], 2)]},
           "rows": rows}
    Path(args.out).write_text(json.dumps(out, indent=1) + "\n")


if __name__ == "__main__":
    main()
