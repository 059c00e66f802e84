"""What moving a vectorized group's observations and actions costs per chunk, on the host (no physics).

    python benchmarks/vector_transfer.py --envs 128,256,512 --repeat 30

For ``--envs`` environments in one group and two observation kinds — ``state`` (PickCube's 42 floats) and
``rgb64`` (a 3 x 64 x 64 image in [0, 1] as float32, 29 proprioception values and 16 instruction tokens, as
``configs/maniskill_rgb.toml`` sends them) — it times, per chunk of ``--chunk`` steps:

* ``pipe``: the group's process answering a chunk with its :class:`~ebrl.envs.vector.VectorChunk`, the
  observations written to shared memory and copied out by the sim service, the rest pickled over the worker
  pipe (what :class:`~ebrl.envs.vector.VectorWorker` does), minus the same round trip with an empty answer;
  ``pickled_pipe``: the same with the observations pickled through the pipe too (the first version);
* ``exchange``: the sim service publishing the group's :class:`~ebrl.messages.Observation` on the bus and
  receiving the :class:`~ebrl.messages.ActionChunk` that answers it from another process over a real Zenoh
  session on loopback (encode, send, validate and decode both ways; the answering process does no forward pass);
* ``bookkeeping``: the sim service's group loop taking the chunk in (``VectorGroupLoop.step`` with the batch and
  the exchange answered at once): counts, finished episodes, each env's decision into its segment
  (:class:`~ebrl.sched.rollout.SegmentBuffers`) and the segments that end published, packed, on a Zenoh session;
  the mean over ``--segment-length`` chunks, so one cut of every env's segment is in it. ``envwise_bookkeeping``:
  the same with the env-by-env loop (``GroupLoop``, a :class:`~ebrl.sched.rollout.SegmentBuilder` and a message per
  env), what vectorized groups ran before;
* ``decode``: training's side of one cut, every env's segment: decoding the packed message and unpacking its
  segments; ``envwise_decode``: decoding one message per env, as before.

The bytes column is the observation message's payload. Divided by the time GPU PhysX takes for one chunk of
the same group (measured on the GPU machine: ``benchmarks/gpu/check.sh maniskill``), these say whether the
bytes path is below 10 % of the step or CUDA IPC is worth building. Results: benchmarks/results/vector_transfer.json.
"""

from __future__ import annotations

import argparse
import asyncio
import json
import multiprocessing as mp
import os
import statistics
import subprocess
import sys
import time
from pathlib import Path

import numpy as np

sys.path.insert(0, str(Path(__file__).resolve().parent.parent))

from ebrl import keys  # noqa: E402
from ebrl.bus.session import Bus, BusOptions
from ebrl.envs.worker import VectorChunk  # noqa: E402
from ebrl.messages import (ActionChunk, Observation, SegmentBatch, TrajectorySegment, decode_message,  # noqa: E402
                           encode_message)
from ebrl.meter import Meter  # noqa: E402
from ebrl.sched.fleet import RolloutStats  # noqa: E402
from ebrl.sched.group import GroupLoop, SegmentOutbox, VectorGroupLoop  # noqa: E402
from ebrl.sched.rollout import Episodes  # noqa: E402
from ebrl.testing import free_port  # noqa: E402

RESULTS = Path(__file__).resolve().parent / "results"
KINDS = {"state": 42, "rgb64": 3 * 64 * 64 + 29 + 16}
ACTION_DIM = 8  # the Panda's joint deltas and gripper


def fake_chunk(n: int, dim: int, ended: int, rng: np.random.Generator) -> VectorChunk:
    """A chunk of ``n`` envs, ``ended`` of them at an episode's end (their final observations travel too)."""
    idx = np.arange(ended)
    return VectorChunk(rng.random(n, np.float32), np.full(n, 4), np.zeros(n, bool), np.arange(n) < ended,
                       np.zeros(n, np.int64),
                       rng.random((n, dim), np.float32), idx, rng.random((ended, dim), np.float32),
                       rng.random(ended), np.full(ended, 50), np.ones(ended, np.int8), 0.01, (0.0,) * 4)


def _pipe_child(conn, n: int, dim: int, ended: int, shared) -> None:
    chunk = fake_chunk(n, dim, ended, np.random.default_rng(0))
    if shared is not None:  # as a vectorized group's process does: the observations into shared memory
        out = np.frombuffer(shared, np.float32).reshape(2, n, dim)
        next_obs, final_obs = chunk.next_obs, chunk.final_obs
        chunk.next_obs = chunk.final_obs = None
    while True:
        cmd = conn.recv()
        if cmd is None:
            return
        if cmd == "chunk" and shared is not None:
            out[0] = next_obs
            out[1, :ended] = final_obs
        conn.send(chunk if cmd == "chunk" else b"")


def pipe_ms(n: int, dim: int, ended: int, repeat: int, shared_memory: bool = True) -> float:
    """One chunk's results from a group's process to the sim service: observations through shared memory (as
    :class:`~ebrl.envs.vector.VectorWorker` does) or pickled through the pipe."""
    ctx = mp.get_context("forkserver")
    parent, child = ctx.Pipe()
    shared = ctx.RawArray("f", 2 * n * dim) if shared_memory else None
    view = None if shared is None else np.frombuffer(shared, np.float32).reshape(2, n, dim)
    proc = ctx.Process(target=_pipe_child, args=(child, n, dim, ended, shared), daemon=True)
    proc.start()

    def round_trip(cmd: str) -> float:
        t0 = time.perf_counter()
        parent.send(cmd)
        reply = parent.recv()
        if view is not None and cmd == "chunk":  # the sim service copies them out (the next chunk overwrites them)
            reply.next_obs, reply.final_obs = view[0].copy(), view[1, :ended].copy()
        return time.perf_counter() - t0

    try:
        for _ in range(3):
            round_trip("chunk")
        full = statistics.median(round_trip("chunk") for _ in range(repeat))
        empty = statistics.median(round_trip("empty") for _ in range(repeat))
        return max(0.0, full - empty) * 1e3
    finally:
        parent.send(None)
        proc.join(5)


def _answerer(port: int, n: int, k: int) -> None:
    """Gen's side without the forward pass: an ActionChunk of the right size for every Observation."""
    async def main() -> None:
        bus = Bus(BusOptions(listen=["tcp/127.0.0.1:0"], connect=[f"tcp/127.0.0.1:{port}"]))
        sub = bus.subscribe(keys.obs("xfer"), Observation, capacity=4)
        rng = np.random.default_rng(1)
        actions = rng.random((n, k, ACTION_DIM), np.float32)
        logprobs, values, latents = rng.random(n, np.float32), rng.random(n, np.float32), np.zeros((n, 0), np.float32)
        bus.declare_token(keys.live("xfer", "answer", 0))
        async for _, msg in sub:  # until the benchmark ends this process
            await bus.put(keys.act("xfer", msg.group), ActionChunk(msg.group, msg.seq, 1, actions, logprobs, values,
                                                                   latents), express=True)

    asyncio.run(main())


async def exchange_ms(n: int, dim: int, k: int, repeat: int) -> tuple[float, int]:
    port = free_port()
    bus = Bus(BusOptions(listen=[f"tcp/127.0.0.1:{port}"]))
    live: dict[str, bool] = {}
    bus.watch_liveliness(keys.live("xfer", "answer", "*"), live.__setitem__)
    proc = mp.get_context("spawn").Process(target=_answerer, args=(port, n, k), daemon=True)
    proc.start()
    try:
        deadline = time.monotonic() + 60
        while not live.get(keys.live("xfer", "answer", 0)):
            if time.monotonic() > deadline:
                raise RuntimeError("the answering process did not come up in 60 s")
            await asyncio.sleep(0.05)
        answers = bus.subscribe(keys.act("xfer", 0), ActionChunk, capacity=4)
        obs = np.random.default_rng(2).random((n, dim), np.float32)
        env_ids = np.arange(n, dtype=np.int64)
        size = len(encode_message(Observation(0, 0, env_ids, obs, 0.0)))
        times = []
        for seq in range(repeat + 3):
            t0 = time.perf_counter()
            await bus.put(keys.obs("xfer", 0), Observation(0, seq, env_ids, obs, time.time()), express=True)
            while True:
                _, chunk = await asyncio.wait_for(answers.next(), 30)
                if chunk.seq == seq:
                    break
            if seq >= 3:
                times.append(time.perf_counter() - t0)
        return statistics.median(times) * 1e3, size
    finally:
        proc.kill()
        proc.join(10)
        await bus.close()


class _Meter(Meter):
    """The sim service's counters; spans and events are not what is timed here."""

    def publish_span(self, *args: object, **kwargs: object) -> None:
        pass

    def event(self, *args: object) -> None:
        pass


class _Batch:
    """A vectorized fleet whose batch answers every chunk at once with ``chunk`` (the physics is not timed)."""

    def __init__(self, n: int, chunk: VectorChunk):
        self.n, self.chunk, self.episodes = n, chunk, Episodes(range(n))

    def env_ids(self, g: int) -> np.ndarray:
        return np.arange(self.n, dtype=np.int64)

    def given_up_env(self, env: int) -> bool:
        return False

    def saw_version(self, version: int) -> None:
        pass

    async def run_vector_chunk(self, g: int, actions: np.ndarray) -> tuple[VectorChunk, float]:
        return self.chunk, 0.0

    async def run_chunk(self, g: int, active: list[int], actions: np.ndarray) -> tuple[list, list[float]]:
        return self.chunk.results(), [0.0] * self.n


class _Answer:
    def __init__(self, chunk: ActionChunk):
        self.chunk = chunk

    async def exchange(self, g: int, seq: int, env_ids: np.ndarray, obs: np.ndarray) -> ActionChunk:
        return self.chunk


class _Iterations:
    def length(self, hosts: int) -> int:
        return 1 << 30  # no iteration boundary: segments are cut at segment_length


async def _loop_ms(n: int, dim: int, k: int, ended: int, repeat: int, envwise: bool, length: int,
                   keep: bool = False) -> tuple[float, list[bytes]]:
    """Per chunk, the group loop's host time; ``keep``: also the payloads it published (not then timed)."""
    rng = np.random.default_rng(3)
    chunk = fake_chunk(n, dim, ended, rng)
    answer = ActionChunk(0, 0, 1, rng.random((n, k, ACTION_DIM), np.float32), rng.random(n, np.float32),
                         rng.random(n, np.float32), np.zeros((n, 0), np.float32))
    bus, meter, sent = Bus(BusOptions(listen=["tcp/127.0.0.1:0"])), _Meter(spans=False), []
    outbox = SegmentOutbox(bus, meter, 1 << 40, lambda: True)
    put = bus.put

    async def keep_payload(key: str, msg: object, **kwargs: object) -> None:  # for the decode column
        sent.append(encode_message(msg))
        await put(key, msg, **kwargs)

    if keep:
        bus.put = keep_payload  # type: ignore[method-assign]
    loop = (GroupLoop if envwise else VectorGroupLoop)(0, _Batch(n, chunk), _Answer(answer), outbox, RolloutStats(),
                                                         meter, "xfer", _Iterations(), length, lambda: 1)
    obs = rng.random((n, dim), np.float32)
    try:
        for _ in range(length):  # warm-up: one cut of every segment
            await loop.step(obs)
        times = []
        for _ in range(max(1, repeat // length)):
            sent.clear()
            t0 = time.perf_counter()
            for _ in range(length):
                await loop.step(obs)
            times.append((time.perf_counter() - t0) / length)
        return statistics.median(times) * 1e3, list(sent)
    finally:
        await bus.close()


def bookkeeping_ms(n: int, dim: int, k: int, ended: int, repeat: int, envwise: bool = False,
                   length: int = 8) -> float:
    """The sim service's host time per chunk of a vectorized group of ``n`` envs (see the module's doc)."""
    return asyncio.run(_loop_ms(n, dim, k, ended, repeat, envwise, length))[0]


def decode_ms(n: int, dim: int, k: int, ended: int, repeat: int, envwise: bool = False, length: int = 8
              ) -> float:
    """Training's decoding of one cut's segments (every env's, at ``length`` decisions), as sent."""
    payloads = asyncio.run(_loop_ms(n, dim, k, ended, length, envwise, length, keep=True))[1]
    cls = TrajectorySegment if envwise else SegmentBatch
    times = []
    for _ in range(max(1, repeat // 4)):
        t0 = time.perf_counter()
        for payload in payloads:
            msg = decode_message(cls, payload)
            if isinstance(msg, SegmentBatch):
                msg.segments()
        times.append(time.perf_counter() - t0)
    return statistics.median(times) * 1e3


def _commit() -> str:
    try:
        return subprocess.run(["git", "rev-parse", "--short", "HEAD"], cwd=Path(__file__).resolve().parent,
                              capture_output=True, text=True, timeout=10).stdout.strip()
    except (OSError, subprocess.SubprocessError):
        return ""


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    parser.add_argument("--envs", default="128,256,512", help="envs per group")
    parser.add_argument("--chunk", type=int, default=4, help="K: steps per chunk")
    parser.add_argument("--ended", type=float, default=0.08, help="share of envs whose episode ends in a chunk "
                        "(PickCube: 50-step episodes, 4-step chunks)")
    parser.add_argument("--segment-length", type=int, default=8, help="decisions per segment (sim.segment_length)")
    parser.add_argument("--repeat", type=int, default=30)
    parser.add_argument("--kinds", default=",".join(KINDS), help="observation kinds: " + ", ".join(KINDS))
    parser.add_argument("--out", default=str(RESULTS / "vector_transfer.json"))
    args = parser.parse_args()
    rows = []
    for kind in args.kinds.split(","):
        dim = KINDS[kind]
        for n in (int(x) for x in args.envs.split(",")):
            ended = max(1, int(round(args.ended * n)))
            book = {f"{prefix}{name}_ms": round(fn(n, dim, args.chunk, ended, args.repeat, envwise=bool(prefix),
                                                    length=args.segment_length), 3)
                    for name, fn in (("bookkeeping", bookkeeping_ms), ("decode", decode_ms))
                    for prefix in ("", "envwise_")}
            row = {"kind": kind, "envs": n, "obs_values": dim,
                   "pipe_ms": round(pipe_ms(n, dim, ended, args.repeat), 3),
                   "pickled_pipe_ms": round(pipe_ms(n, dim, ended, args.repeat, shared_memory=False), 3), **book}
            ms, size = asyncio.run(exchange_ms(n, dim, args.chunk, args.repeat))
            row.update(exchange_ms=round(ms, 3), obs_bytes=size)
            row["total_ms"] = round(row["pipe_ms"] + row["exchange_ms"] + row["bookkeeping_ms"], 3)
            row["per_step_ms"] = round(row["total_ms"] / args.chunk, 3)
            rows.append(row)
            print(f"{kind:6s} {n:4d} envs: obs {size / 1e6:7.2f} MB | pipe {row['pipe_ms']:7.2f} ms (pickled "
                  f"{row['pickled_pipe_ms']:7.2f}) | exchange {row['exchange_ms']:7.2f} ms | bookkeeping "
                  f"{row['bookkeeping_ms']:7.2f} ms (env by env {row['envwise_bookkeeping_ms']:7.2f}) | decode a cut "
                  f"{row['decode_ms']:7.2f} ms (env by env {row['envwise_decode_ms']:7.2f}) | per step "
                  f"{row['per_step_ms']:6.2f} ms", flush=True)
    out = {"command": " ".join(["python", *sys.argv]), "chunk": args.chunk, "segment_length": args.segment_length,
           "commit": _commit(), "machine": f"{len(os.sched_getaffinity(0))} usable cores",
           "date": time.strftime("%Y-%m-%d"), "rows": rows}
    Path(args.out).parent.mkdir(parents=True, exist_ok=True)
    Path(args.out).write_text(json.dumps(out, indent=2) + "\n")
    print(f"wrote {args.out}")


if __name__ == "__main__":
    main()
