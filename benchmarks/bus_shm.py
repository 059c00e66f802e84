"""Bulk payloads between processes of one host: Zenoh's shared-memory transport against copies (issue 51).

    python benchmarks/bus_shm.py --json benchmarks/results/bus_shm.json

The path a run's messages take by default: a client session signed in as ``sim/0`` publishes on its trajectory key,
the launcher's router (``bus.mode = "client"``, with the run's access rules) forwards it, a client signed in as
``train/0`` receives it, all three on loopback. Zenoh 1.x puts a payload over 3 KB into a shared-memory pool on its
own (``transport/shared_memory``, enabled by default, which ``ebrl.bus.options.zenoh_config`` keeps): then only a
reference crosses the sockets. For each size, after 200 messages of warm-up, ``--messages`` messages with shared
memory on and off (``transport/shared_memory/enabled``), sizes interleaved; MB/s received.
"""

from __future__ import annotations

import argparse
import json
import os
import sys
import tempfile
import threading
import time
from pathlib import Path

ROOT = Path(__file__).resolve().parent.parent
sys.path.insert(0, str(ROOT))

import zenoh  # noqa: E402

from ebrl import bench  # noqa: E402
from ebrl import keys  # noqa: E402
from ebrl.bus import auth  # noqa: E402
from ebrl.bus.session import BusOptions, zenoh_config  # noqa: E402
from ebrl.testing import free_port  # noqa: E402

LEADS = (("sim", 0), ("train", 0))
WARM_UP = 200


def sessions(tmp: Path, shm: bool) -> list[zenoh.Session]:
    """The launcher's router, sim/0's client and train/0's client, signed in as a run's are."""
    tmp = Path(tempfile.mkdtemp(dir=tmp))  # a run's own secret each time
    secret = auth.create(tmp / "bus.secret")
    dictionary = auth.write_router_dictionary(secret, tmp / "bus.router-0.secret", LEADS)
    endpoint = f"tcp/127.0.0.1:{free_port()}"
    options = [BusOptions(mode="router", listen=[endpoint], secret_file=str(secret), role="launcher", run="r",
                          instances=LEADS, dictionary_file=str(dictionary), groups=1)]
    options += [BusOptions(mode="client", connect=[endpoint], listen=[], role=role,
                           identity=auth.instance_line(secret, role, n)) for role, n in LEADS]
    out = []
    for option in options:
        config = zenoh_config(option)
        config.insert_json5("transport/shared_memory/enabled", json.dumps(shm))
        out.append(zenoh.open(config))
    return out


def rate(tmp: Path, shm: bool, size: int, messages: int) -> float:
    """MB/s received from sim/0 to train/0 through the router."""
    router, sim, train = sessions(tmp, shm)
    got = [0]
    done = threading.Event()

    def received(_sample: zenoh.Sample) -> None:
        got[0] += 1
        if got[0] == WARM_UP + messages:
            done.set()

    try:
        sub = train.declare_subscriber(keys.traj("r"), received)  # noqa: F841 (kept declared)
        pub = sim.declare_publisher(keys.traj("r", 0), congestion_control=zenoh.CongestionControl.BLOCK)
        payload = bytes(size)
        deadline = time.monotonic() + 30
        while got[0] == 0:  # until the subscription has reached the publisher
            pub.put(payload)
            time.sleep(0.01)
            if time.monotonic() > deadline:
                raise RuntimeError("nothing arrived in 30 s")
        got[0] = 0
        for _ in range(WARM_UP):
            pub.put(payload)
        while got[0] < WARM_UP:
            time.sleep(0.001)
        start = time.perf_counter()
        for _ in range(messages):
            pub.put(payload)
        if not done.wait(120):
            raise RuntimeError(f"{got[0] - WARM_UP} of {messages} messages arrived")
        return messages * size / (time.perf_counter() - start) / 1e6
    finally:
        for session in (sim, train, router):
            session.close()


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--sizes", default="4096,16384,65536,262144,1048576", help="payload bytes, comma-separated")
    parser.add_argument("--messages", type=int, default=2000)
    parser.add_argument("--json", default=str(ROOT / "benchmarks" / "results" / "bus_shm.json"))
    args = parser.parse_args()
    rows = []
    with tempfile.TemporaryDirectory() as tmp:
        for size in (int(s) for s in args.sizes.split(",")):
            on, off = rate(Path(tmp), True, size, args.messages), rate(Path(tmp), False, size, args.messages)
            rows.append({"bytes": size, "shm_mb_per_s": round(on, 1), "copy_mb_per_s": round(off, 1),
                         "ratio": round(on / off, 2)})
            print(f"{size:>9} bytes: shared memory {on:8.0f} MB/s, copies {off:8.0f} MB/s ({on / off:.2f}x)", flush=True)
    Path(args.json).write_text(json.dumps({
        "command": "python benchmarks/bus_shm.py " + " ".join(sys.argv[1:]), "commit": bench.commit(),
        "machine": f"{len(os.sched_getaffinity(0))} usable cores", "date": time.strftime("%Y-%m-%d"),
        "zenoh": zenoh.__version__ if hasattr(zenoh, "__version__") else "", "messages": args.messages,
        "rows": rows}, indent=1) + "\n")
    print(f"wrote {args.json}")


if __name__ == "__main__":
    main()
