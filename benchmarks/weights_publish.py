"""Weight-publish latency vs model size: one message vs parts, and what each costs the two event loops.

    python benchmarks/weights_publish.py                              # ~3 min, 1-500 MB
    python benchmarks/weights_publish.py --sizes-mb 1 10 --versions 3 --variants parts

Two processes on loopback, like train and gen: this one publishes float32 state
dicts (8 weight matrices and 8 biases) of each size; a subscriber process
receives them with ``ebrl.weights.WeightsReceiver`` and acknowledges each
version once its event loop holds the arrays, ready to load. Variants, taken
in turn for every version (side by side, same run):

* ``inline``: what train did before ``ebrl.weights``: encode one ``Weights``
  message on the event loop, then ``bus.put_bytes``;
* ``whole``: one ``Weights`` message, encoded and sent on the publisher's thread;
* ``parts``: ``WeightsPart`` messages of 4 MiB (the default over 4 MiB);
* ``<variant>@<MiB>``: the same with Zenoh's shared-memory pool of that size
  (``transport/shared_memory/transport_optimization/pool_size``; default 16).

The subscriber then loads each version into torch layers on a one-thread pool, as
generation does between batches, and reports how long that took.

Per version: latency from the start of encoding until the subscriber's event
loop holds the decoded arrays; the longest gap of a 1 ms ticker on each event
loop meanwhile (the publisher's until the acknowledgement arrives; the
subscriber's while the version arrives), which is how long generation would
have stalled. The first version of each size and variant is reported apart
(cold: first-touch page faults, pool set-up); median and p90 are over the rest.

Results go to benchmarks/results/weights_publish.json.
"""

from __future__ import annotations

import argparse
import asyncio
import collections
import concurrent.futures
import importlib.metadata
import json
import multiprocessing as mp
import os
import platform
import resource
import statistics
import sys
import time
from pathlib import Path

import numpy as np
import torch
import zenoh

sys.path.insert(0, str(Path(__file__).resolve().parent.parent))

from ebrl import keys  # noqa: E402
from ebrl.bus.session import Bus, BusOptions, zenoh_config
from ebrl.bus.endpoints import free_port  # noqa: E402
from ebrl.messages import Weights, encode_message  # noqa: E402
from ebrl.policies import load_arrays  # noqa: E402
from ebrl.weights import PART_BYTES, SINGLE_MAX_BYTES, WeightsPublisher, WeightsReceiver  # noqa: E402

RESULTS = Path(__file__).resolve().parent / "results"
RUN = "wbench"
ACK_KEY = "bench/weights/ack"
TOKEN_KEY = "bench/weights/gen"
DEFAULT_POOL_MIB = 16


class Ticker:
    """A task that sleeps 1 ms in a loop and remembers when each tick ended and how long it took."""

    def __init__(self) -> None:
        self.ticks: collections.deque[tuple[float, float]] = collections.deque(maxlen=200_000)
        self.task = asyncio.ensure_future(self._run())

    async def _run(self) -> None:
        while True:
            start = time.perf_counter()
            await asyncio.sleep(0.001)
            end = time.perf_counter()
            self.ticks.append((time.time(), end - start))

    def max_gap_ms(self, since: float, until: float) -> float:
        return 1e3 * max((gap for end, gap in self.ticks if since <= end <= until), default=0.0)


def bus_options(port: int, listen: bool) -> BusOptions:
    if listen:
        return BusOptions(listen=[f"tcp/127.0.0.1:{port}"])
    return BusOptions(listen=["tcp/127.0.0.1:0"], connect=[f"tcp/127.0.0.1:{port}"])


def open_bus(options: BusOptions, pool_mib: int) -> Bus:
    conf = zenoh_config(options)
    conf.insert_json5("transport/shared_memory/transport_optimization/pool_size", str(pool_mib << 20))
    return Bus(options, session=zenoh.open(conf))


def peak_rss_mb() -> float:
    return resource.getrusage(resource.RUSAGE_SELF).ru_maxrss / 1024


# --- the subscriber (gen's side) ---------------------------------------------------------


def subscriber(port: int, done, out) -> None:
    async def main() -> None:
        bus = Bus(bus_options(port, listen=True))
        wake = asyncio.Event()
        receiver = WeightsReceiver(bus, RUN, notify=wake)
        ticker = Ticker()
        await asyncio.sleep(2.0)
        idle = ticker.max_gap_ms(0, time.time())
        bus.declare_token(TOKEN_KEY)
        stopped = asyncio.ensure_future(asyncio.get_running_loop().run_in_executor(None, done.wait))
        version = -1
        pool = concurrent.futures.ThreadPoolExecutor(1, thread_name_prefix="gen-forward")
        layers = None
        while not stopped.done():
            waiting = asyncio.ensure_future(wake.wait())
            await asyncio.wait([waiting, stopped], return_when=asyncio.FIRST_COMPLETED)
            waiting.cancel()
            wake.clear()
            weights = receiver.take_newer(version)
            if weights is None:
                continue
            ready_at = time.time()
            version, created_at = weights.version, weights.created_at
            intact = all(a.flat[0] == version for a in weights.params.values())
            total = sum(a.nbytes for a in weights.params.values())
            if layers is None or sum(p.nbytes for p in layers.state_dict().values()) != total:
                layers = None  # one model at a time in memory
                layers = await asyncio.get_running_loop().run_in_executor(pool, model, weights.params)
            start = time.time()
            await asyncio.get_running_loop().run_in_executor(pool, load_arrays, layers, weights.params)
            loaded_at = time.time()
            del weights
            await asyncio.sleep(0.003)  # let the ticker record the tick that spans loaded_at
            ack = {"version": version, "ready_at": ready_at, "intact": intact, "bytes": total,
                   "max_gap_ms": ticker.max_gap_ms(created_at, ready_at + 0.002), "load_s": loaded_at - start,
                   "load_max_gap_ms": ticker.max_gap_ms(start, loaded_at + 0.002)}
            await bus.put_bytes(ACK_KEY, json.dumps(ack).encode())
        out.put({"idle_max_gap_ms": idle, "peak_rss_mb": peak_rss_mb(), "malformed": dict(bus.malformed),
                 "discarded": receiver.discarded})
        await bus.close()

    asyncio.run(main())


# --- the publisher (train's side) ----------------------------------------------------------


def state_dict(size_mb: float, rng: np.random.Generator) -> dict[str, np.ndarray]:
    """The state dict of :func:`model`: 8 layers of float32, size/8 each."""
    rows = max(1, int(size_mb * 1e6 / 4 / 8) // 1025)
    out = {}
    for layer in range(8):
        out[f"{layer}.weight"] = rng.random((rows, 1024), dtype=np.float32)
        out[f"{layer}.bias"] = rng.random(rows, dtype=np.float32)
    return out


def model(params: dict[str, np.ndarray]) -> torch.nn.Module:
    """Uninitialised torch layers shaped like ``params`` (what generation loads into)."""
    rows = len(params["0.bias"])
    return torch.nn.Sequential(*[torch.nn.Linear(1024, rows, device="meta") for _ in range(8)]).to_empty(device="cpu")


def parse_variant(spec: str) -> tuple[str, int]:
    name, _, pool = spec.partition("@")
    if name not in ("inline", "whole", "parts"):
        raise SystemExit(f"unknown variant {spec!r}: expected inline, whole or parts, optionally @<pool MiB>")
    return name, int(pool or DEFAULT_POOL_MIB)


async def publish_all(args, port: int) -> list[dict]:
    """Every variant in turn for each version; one publishing session per pool size, all connected at once."""
    ticker = Ticker()
    acks: asyncio.Queue = asyncio.Queue()
    peers: dict[int, tuple[Bus, dict[str, WeightsPublisher]]] = {}
    for pool_mib in sorted({parse_variant(spec)[1] for spec in args.variants}):
        bus = open_bus(bus_options(port, listen=False), pool_mib)
        seen = asyncio.Event()
        bus.watch_liveliness(TOKEN_KEY, lambda key, alive: seen.set() if alive else None)
        await asyncio.wait_for(seen.wait(), 60)
        if not peers:
            bus.subscribe_raw(ACK_KEY, lambda key, payload: ticker.task.get_loop().call_soon_threadsafe(
                acks.put_nowait, json.loads(payload)))
        peers[pool_mib] = bus, {"parts": WeightsPublisher(bus, RUN),
                                "whole": WeightsPublisher(bus, RUN, single_max_bytes=1 << 62)}
    await asyncio.sleep(0.5)
    rows = []
    version = 0
    rng = np.random.default_rng(0)
    for size in args.sizes_mb:
        arrays = state_dict(size, rng)
        total = sum(a.nbytes for a in arrays.values())
        for round_ in range(args.versions):
            for spec in args.variants:
                version += 1
                for array in arrays.values():
                    array.flat[0] = version
                name, pool_mib = parse_variant(spec)
                bus, publishers = peers[pool_mib]
                start = time.time()
                if name == "inline":
                    payload = encode_message(Weights(version=version, params=arrays, created_at=start))
                    await bus.put_bytes(keys.weights(RUN), payload)
                    del payload
                    sent = {"mode": "whole", "parts": 1}
                else:
                    stats = await publishers[name].publish(version, arrays, created_at=start)
                    sent = {"mode": stats.mode, "parts": stats.parts, "pack_s": stats.pack_s, "send_s": stats.send_s}
                returned = time.time()
                ack = await asyncio.wait_for(acks.get(), args.timeout)
                acked = time.time()
                if ack["version"] != version or not ack["intact"] or ack["bytes"] != total:
                    raise SystemExit(f"version {version}: the subscriber acknowledged {ack}")
                row = {"variant": spec, "size_mb": size, "bytes": total, "version": version, "cold": round_ == 0,
                       "latency_s": ack["ready_at"] - start, "publish_return_s": returned - start,
                       "pub_max_gap_ms": ticker.max_gap_ms(start, acked), "sub_max_gap_ms": ack["max_gap_ms"],
                       "load_s": ack["load_s"], "load_max_gap_ms": ack["load_max_gap_ms"], **sent}
                rows.append(row)
                print(f"{spec:>10} {size:6.0f} MB v{version:<4} latency {row['latency_s'] * 1e3:8.1f} ms  "
                      f"loop gap pub {row['pub_max_gap_ms']:7.1f} ms  sub {ack['max_gap_ms']:7.1f} ms  "
                      f"load {ack['load_s'] * 1e3:7.1f} ms", flush=True)
        del arrays
    for bus, publishers in peers.values():
        for publisher in publishers.values():
            publisher.close()
        await bus.close()
    ticker.task.cancel()
    return rows


def summarize(rows: list[dict]) -> list[dict]:
    out = []
    groups: dict[tuple[str, float], list[dict]] = collections.defaultdict(list)
    for row in rows:
        groups[(row["variant"], row["size_mb"])].append(row)
    for (variant, size), group in groups.items():
        warm = [r for r in group if not r["cold"]] or group
        lat = sorted(r["latency_s"] for r in warm)
        out.append({
            "variant": variant, "size_mb": size, "versions": len(warm),
            "latency_median_ms": round(1e3 * statistics.median(lat), 1),
            "latency_p90_ms": round(1e3 * lat[min(len(lat) - 1, int(0.9 * len(lat)))], 1),
            "latency_cold_ms": round(1e3 * group[0]["latency_s"], 1),
            "throughput_mb_per_s": round(size / statistics.median(lat), 1),
            "pub_loop_max_gap_ms": round(max(r["pub_max_gap_ms"] for r in group), 1),
            "pub_loop_max_gap_median_ms": round(statistics.median(r["pub_max_gap_ms"] for r in warm), 1),
            "sub_loop_max_gap_ms": round(max(r["sub_max_gap_ms"] for r in group), 1),
            "sub_loop_max_gap_median_ms": round(statistics.median(r["sub_max_gap_ms"] for r in warm), 1),
            "load_median_ms": round(1e3 * statistics.median(r["load_s"] for r in warm), 1),
            "load_loop_max_gap_ms": round(max(r["load_max_gap_ms"] for r in group), 1),
        })
    return out


def print_table(summary: list[dict]) -> None:
    print("\n| size MB | variant | latency median ms | p90 ms | cold ms | MB/s | pub loop max gap ms (median/max) "
          "| sub loop max gap ms (median/max) | load ms |")
    print("|---|---|---|---|---|---|---|---|---|")
    for s in sorted(summary, key=lambda s: (s["size_mb"], s["variant"])):
        print(f"| {s['size_mb']:g} | {s['variant']} | {s['latency_median_ms']} | {s['latency_p90_ms']} | "
              f"{s['latency_cold_ms']} | {s['throughput_mb_per_s']} | {s['pub_loop_max_gap_median_ms']}/"
              f"{s['pub_loop_max_gap_ms']} | {s['sub_loop_max_gap_median_ms']}/{s['sub_loop_max_gap_ms']} | "
              f"{s['load_median_ms']} |")


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    parser.add_argument("--sizes-mb", type=float, nargs="+", default=[1, 10, 100, 250, 500])
    parser.add_argument("--versions", type=int, default=6, help="versions per size and variant, the first cold")
    parser.add_argument("--variants", type=lambda s: s.split(","), default="inline,whole,parts,whole@256,parts@256")
    parser.add_argument("--timeout", type=float, default=120.0, help="seconds to wait for one acknowledgement")
    parser.add_argument("--out", default=str(RESULTS / "weights_publish.json"))
    args = parser.parse_args()
    for spec in args.variants:
        parse_variant(spec)
    port = free_port()
    load_start = round(os.getloadavg()[0], 2)  # other work on the machine shows up as noise
    ctx = mp.get_context("spawn")
    done, out = ctx.Event(), ctx.Queue()
    proc = ctx.Process(target=subscriber, args=(port, done, out))
    proc.start()
    try:
        started = time.time()
        rows = asyncio.run(publish_all(args, port))
        elapsed = time.time() - started
        done.set()
        sub = out.get(timeout=60)
    finally:
        done.set()
        proc.join(30)
        if proc.is_alive():
            proc.kill()
    summary = summarize(rows)
    print_table(summary)
    result = {
        "command": "python benchmarks/weights_publish.py " + " ".join(sys.argv[1:]),
        "machine": {"platform": platform.platform(), "cores": os.cpu_count(),
                    "memory_gb": round(os.sysconf("SC_PAGE_SIZE") * os.sysconf("SC_PHYS_PAGES") / 1e9, 1)},
        "zenoh": importlib.metadata.version("eclipse-zenoh"), "part_bytes": PART_BYTES,
        "single_max_bytes": SINGLE_MAX_BYTES, "elapsed_s": round(elapsed, 1),
        "load_average_1min": {"start": load_start, "end": round(os.getloadavg()[0], 2)},
        "publisher_peak_rss_mb": round(peak_rss_mb(), 1),
        "subscriber": sub, "summary": summary, "versions": rows,
    }
    Path(args.out).parent.mkdir(parents=True, exist_ok=True)
    Path(args.out).write_text(json.dumps(result, indent=2) + "\n")
    print(f"written {args.out}")


if __name__ == "__main__":
    main()
