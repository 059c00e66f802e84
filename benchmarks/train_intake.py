"""Training's host work per update besides the gradient steps: a config's batch arriving as segments, taken in.

    python benchmarks/train_intake.py --out benchmarks/results/train_intake.json

For one update's worth of decisions (``train.batch_size``) of the config's task and policy, arriving as its
vectorized groups send them (``sim.groups`` x ``sim.envs_per_group`` envs, segments of up to
``sim.segment_length`` decisions, cut early where an episode of the task's time limit ends, every env at its own
point of its episode), it times what the train service's host does with them:

* ``decode_accept``: decoding each packed :class:`~ebrl.messages.SegmentBatch` (``obswire`` is not involved for
  state observations) and ``Learner.accept``, on the service's event loop, while an update may be running on the
  update thread (both hold the GIL);
* ``take``: ``Learner.take``, the collector cutting the batch (stale prefixes, the split at ``batch_size``);
* ``build``: the collector building the batch (GAE, concatenation) with the critic answered at once, so only host
  work is timed (on a GPU the critic's forward pass is the device's).

``envwise`` (``--intakes``) accepts the segments one at a time: what the train service did with packed messages
before, and what it does with the segments of groups that are not vectorized. The intakes run in interleaved
rounds; each row is the median over its updates. ``EBRL_SRC=<checkout>`` times another checkout's ``ebrl``: how
``train_intake_before.json`` was measured, at 45fb9c6, before GAE over all segments at once and the packed intake
(``--intakes envwise``, a git worktree of that commit).
Results: benchmarks/results/train_intake.json, benchmarks/results/train_intake_before.json.
"""

from __future__ import annotations

import argparse
import collections
import json
import os
import platform
import statistics
import subprocess
import sys
import time
from pathlib import Path

import numpy as np
import torch

ROOT = Path(__file__).resolve().parent.parent
sys.path.insert(0, os.environ.get("EBRL_SRC", str(ROOT)))

from ebrl import config as config_mod  # noqa: E402
from ebrl.algos.learner import Learner  # noqa: E402
from ebrl.envs import EnvSpec, describe  # noqa: E402
from ebrl.messages import SegmentBatch, decode_message, encode_message  # noqa: E402


class Counts:
    def __init__(self) -> None:
        self.counts: collections.Counter[str] = collections.Counter()

    def count(self, name: str, n: float = 1) -> None:
        self.counts[name] += n

    def publish_span(self, *args: object) -> None:
        pass


class Critic(torch.nn.Module):
    """Values answered at once: the batch's host work without the forward pass."""

    def __init__(self) -> None:
        super().__init__()
        self.p = torch.nn.Parameter(torch.zeros(1))

    def value(self, obs: torch.Tensor) -> torch.Tensor:
        return torch.zeros(len(obs))


OFFSETS = "episode_offsets" in SegmentBatch.__dataclass_fields__  # training follows episodes by them (returns.py)


def payloads(cfg, info, episode_decisions: int, updates: int, rng: np.random.Generator) -> list[bytes]:
    """Encoded packed messages, one per group per cut, until ``updates`` batches' worth of decisions."""
    n, length, k = cfg.sim.envs_per_group, cfg.sim.segment_length, cfg.policy.chunk
    obs_shape, action_dim, out, total = info.obs_shape, info.action_dim, [], 0
    position = rng.integers(0, episode_decisions, (cfg.sim.groups, n))  # each env's decision within its episode
    episode = np.zeros((cfg.sim.groups, n), np.int64)
    so_far = np.zeros((cfg.sim.groups, n))  # each env's return so far (its first episode's: of what was sent)

    def f(*shape: int) -> np.ndarray:
        return rng.standard_normal(shape).astype(np.float32)

    while total < updates * cfg.train.batch_size:
        for g in range(cfg.sim.groups):
            lengths = np.minimum(length, episode_decisions - position[g]).astype(np.int32)
            offsets = position[g] * k
            position[g] = (position[g] + lengths) % episode_decisions
            ended = position[g] == 0
            t = int(lengths.sum())
            rewards = f(t)
            so_far[g] += np.add.reduceat(rewards.astype(np.float64), np.cumsum(lengths) - lengths)
            out.append(encode_message(SegmentBatch(
                group=g, env_ids=np.arange(n) + g * n, episodes=episode[g].copy(), lengths=lengths,
                ends=np.where(ended, 2, 0).astype(np.int8), obs=f(t, *obs_shape), actions=f(t, k, action_dim),
                latents=np.zeros((t, 0), np.float32), logprobs=f(t), values=f(t), rewards=rewards,
                steps=np.full(t, k, np.int32), versions=np.zeros(t, np.int64), last_obs=f(n, *obs_shape),
                **({"episode_offsets": offsets.astype(np.int64)} if OFFSETS else {}),  # an older checkout: none
                episode_returns=np.where(ended, so_far[g], 0.0).astype(np.float32),
                episode_lengths=np.where(ended, episode_decisions * k, -1).astype(np.int32),
                episode_successes=np.where(ended, rng.integers(0, 2, n), -1).astype(np.int8))))
            episode[g] += ended
            so_far[g][ended] = 0.0
            total += t
    return out


def measure(cfg, info, messages: list[bytes], envwise: bool, updates: int) -> list[tuple[float, float, float]]:
    """Seconds of each part, for each of ``updates`` updates, from a new learner."""
    learner, critic, parts = Learner(cfg, info, 1, Counts(), "/tmp/ebrl-train-intake"), Critic(), []
    queue = collections.deque(messages)
    for _ in range(updates):
        t0 = time.perf_counter()
        while not learner.ready:
            msg = decode_message(SegmentBatch, queue.popleft())
            for item in msg.segments() if envwise else (msg,):
                learner.accept(item, print)
        t1 = time.perf_counter()
        items = learner.take()
        t2 = time.perf_counter()
        learner.collector.build(items, critic)
        t3 = time.perf_counter()
        parts.append((t1 - t0, t2 - t1, t3 - t2))
    return parts


def _commit(where: str) -> str:
    try:
        return subprocess.check_output(["git", "-C", where, "rev-parse", "--short", "HEAD"], text=True).strip()
    except (OSError, subprocess.CalledProcessError):
        return "unknown"


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    parser.add_argument("--config", default="configs/mjwarp_pickcube.toml")
    parser.add_argument("--intakes", default="packed,envwise", help="comma-separated: packed, envwise")
    parser.add_argument("--updates", type=int, default=5, help="updates per intake and round")
    parser.add_argument("--rounds", type=int, default=3, help="rounds, the intakes interleaved in each")
    parser.add_argument("--episode-steps", type=int, default=0,
                        help="env steps of an episode (default: env.max_episode_steps, else 100: PandaPickCube-v0's)")
    parser.add_argument("--out", default=None, help="write the results here (JSON)")
    args = parser.parse_args()
    intakes = [name.strip() for name in args.intakes.split(",") if name.strip()]
    if not intakes or set(intakes) - {"packed", "envwise"}:
        parser.error(f"--intakes {args.intakes!r}: packed and/or envwise")
    torch.set_num_threads(1)
    cfg = config_mod.load(args.config, ['train.device="cpu"'])
    info = describe(EnvSpec.from_config(cfg.env))
    limit = args.episode_steps or cfg.env.max_episode_steps or 100
    episode_decisions = -(-limit // cfg.policy.chunk)
    messages = payloads(cfg, info, episode_decisions, args.updates + 1, np.random.default_rng(0))
    parts: dict[str, list] = {name: [] for name in intakes}
    for _ in range(args.rounds):
        for name in intakes:
            parts[name] += measure(cfg, info, messages, name == "envwise", args.updates)
    rows = []
    for name, measured in parts.items():
        ms = [1e3 * statistics.median(p[i] for p in measured) for i in range(3)]
        rows.append({"intake": name, "decode_accept_ms": ms[0], "take_ms": ms[1], "build_ms": ms[2],
                     "total_ms": sum(ms)})
        print(json.dumps(rows[-1]), flush=True)
    prefix = [f"EBRL_SRC={os.environ['EBRL_SRC']}"] if "EBRL_SRC" in os.environ else []
    out = {"command": " ".join([*prefix, "python", "benchmarks/train_intake.py", *sys.argv[1:]]),
           "commit": _commit(os.environ.get("EBRL_SRC", str(ROOT))),
           "machine": f"{platform.machine()}, {len(os.sched_getaffinity(0))} cores, torch {torch.__version__}",
           "config": args.config, "envs": cfg.sim.groups * cfg.sim.envs_per_group, "batch_size": cfg.train.batch_size,
           "segment_length": cfg.sim.segment_length, "episode_decisions": episode_decisions,
           "updates": args.updates * args.rounds, "rows": rows}
    if args.out:
        Path(args.out).write_text(json.dumps(out, indent=1) + "\n")


if __name__ == "__main__":
    main()
