"""Observability overhead: what spans and stats cost end to end, measured two ways.

    python benchmarks/overhead.py micro                        # CPU cost of one span, publisher + recorder
    python benchmarks/overhead.py e2e --config configs/quickstart.toml --duration 40 --repeat 4

* ``micro`` records spans through a real ``Service`` (batched per lane, as in a
  run) and publishes them to a real recording peer (another process, like the
  launcher), and reads the CPU time both processes spent per span. Multiplied by a run's span rate, that is the share
  of the machine observability takes, free of run-to-run noise.
* ``e2e`` runs ebrl side by side, interleaved: ``on`` (spans published and
  recorded: the default), ``off`` (``viz.spans=false viz.record=false``; stats
  stay, since the launcher needs them), and ``viz`` (``on`` plus the viz service
  saving a rerun recording). It reports env steps/s per variant and the
  median of the per-round on/off ratios.

Results go to benchmarks/results/overhead_*.json.
"""

from __future__ import annotations

import argparse
import asyncio
import json
import multiprocessing as mp
import os
import statistics
import sys
import tempfile
import time
from pathlib import Path

sys.path.insert(0, str(Path(__file__).resolve().parent.parent))

from ebrl import bench  # noqa: E402
from ebrl import keys  # noqa: E402
from ebrl.bus.session import Bus, BusOptions
from ebrl import config as config_mod  # noqa: E402
from ebrl.service import SPAN_FLUSH_S, Service  # noqa: E402
from ebrl.testing import free_port  # noqa: E402
from ebrl.viz.record import Recorder  # noqa: E402

RESULTS = Path(__file__).resolve().parent / "results"
VARIANTS = {
    "on": [],
    "off": ["viz.spans=false", "viz.record=false"],
    "unrecorded": ["viz.record=false"],  # spans published, but nobody subscribes
    "viz": ['viz.rerun="save"'],
}


def _recorder(port: int, path: str, ready, done, out) -> None:
    async def main() -> None:
        bus = Bus(BusOptions(listen=[f"tcp/127.0.0.1:{port}"]))
        rec = Recorder(path)
        bus.subscribe_raw(keys.stats_all("overhead"), rec.write)
        cpu0 = time.process_time()
        ready.set()
        await asyncio.get_running_loop().run_in_executor(None, done.wait)
        rec.close()
        out.put((time.process_time() - cpu0, rec.samples))
        await bus.close()

    asyncio.run(main())


def micro(args) -> dict:
    port = free_port()
    ctx = mp.get_context("spawn")
    ready, done, out = ctx.Event(), ctx.Event(), ctx.Queue()
    with tempfile.TemporaryDirectory() as tmp:
        proc = ctx.Process(target=_recorder, args=(port, os.path.join(tmp, "stats.msgpack"), ready, done, out))
        proc.start()
        ready.wait(30)

        async def publish() -> tuple[float, float, int]:
            # A real Service's span path: publish_span per span, one SpanBatch per lane per flush.
            service = Service(config_mod.from_dict({"run": {"name": "overhead"}}))
            service.bus = bus = Bus(BusOptions(listen=["tcp/127.0.0.1:0"], connect=[f"tcp/127.0.0.1:{port}"]))
            await asyncio.sleep(1.0)  # connected
            per_flush = max(1, int(args.rate * SPAN_FLUSH_S))  # spans recorded between two flushes
            cpu0, t0 = time.process_time(), time.perf_counter()
            for i in range(args.spans):
                now = time.time()
                service.publish_span(f"sim.g{i % 2}", "chunk", now, now)
                if i % per_flush == per_flush - 1:
                    service.flush_spans()
            service.flush_spans()
            await bus.flush()
            cpu = time.process_time() - cpu0
            wall = time.perf_counter() - t0
            dropped = bus.sender_dropped
            await bus.close()
            return cpu, wall, dropped

        pub_cpu, wall, dropped = asyncio.run(publish())
        done.set()
        rec_cpu, samples = out.get(timeout=30)
        proc.join(10)
    result = {
        "spans": args.spans, "span_rate_assumed": args.rate, "messages_recorded": samples, "sender_dropped": dropped,
        "publisher_cpu_us_per_span": 1e6 * pub_cpu / args.spans,
        "recorder_cpu_us_per_span": 1e6 * rec_cpu / args.spans,  # includes the Zenoh receive path
        "wall_s": wall,
    }
    per_span_s = (pub_cpu + rec_cpu) / args.spans
    for rate in (100, 1000, 2000):
        result[f"cores_used_at_{rate}_spans_per_s"] = per_span_s * rate
    return result


def e2e(args) -> dict:
    names = args.variants.split(",")
    runs: dict[str, list[dict]] = {v: [] for v in names}
    for r in range(args.repeat):
        # Interleaved, so that machine drift hits all variants alike; the order alternates round by
        # round, so that no variant always runs first (right after another run's shutdown).
        for v in (names if r % 2 == 0 else names[::-1]):
            print(f"[{r + 1}/{args.repeat}] {v}", file=sys.stderr, flush=True)
            runs[v].append(bench.measure(args.config, "ebrl", [*args.set, *VARIANTS[v]], args.duration))
    med = {v: statistics.median(x["env_steps_per_s"] for x in runs[v]) for v in names}
    result = {"config": args.config, "duration_s": args.duration, "repeat": args.repeat,
              "env_steps_per_s_median": med,
              "traj_per_s_median": {v: statistics.median(x["traj_per_s"] for x in runs[v]) for v in names},
              "runs": runs}
    for v in names:
        if v != "off" and "off" in runs:
            ratios = [a["env_steps_per_s"] / b["env_steps_per_s"] for a, b in zip(runs[v], runs["off"])]
            result[f"{v}_over_off_per_round"] = ratios
            result[f"{v}_over_off_median"] = statistics.median(ratios)
    return result


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    sub = parser.add_subparsers(dest="what", required=True)
    p = sub.add_parser("micro")
    p.add_argument("--spans", type=int, default=50_000)
    p.add_argument("--rate", type=float, default=1000.0, help="spans per second the batching assumes")
    p = sub.add_parser("e2e")
    p.add_argument("--config", default="configs/quickstart.toml")
    p.add_argument("--variants", default="on,off,viz")
    p.add_argument("--duration", type=float, default=40.0)
    p.add_argument("--repeat", type=int, default=4)
    p.add_argument("--set", action="append", default=[], metavar="SECTION.KEY=VALUE")
    p.add_argument("--tag", default="", help="suffix of the result file name")
    args = parser.parse_args()
    result = micro(args) if args.what == "micro" else e2e(args)
    result["command"] = "python benchmarks/overhead.py " + " ".join(sys.argv[1:])
    RESULTS.mkdir(exist_ok=True)
    path = RESULTS / f"overhead_{args.what}{'_' + args.tag if getattr(args, 'tag', '') else ''}.json"
    path.write_text(json.dumps(result, indent=2) + "\n")
    print(json.dumps({k: v for k, v in result.items() if k != "runs"}, indent=2))
    print(f"written to {path}")


if __name__ == "__main__":
    main()
