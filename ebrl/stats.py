"""``ebrl stats``: subscribe to ``ebrl/stats/**`` and print every decoded message."""

from __future__ import annotations

import json
import queue
import signal

import zenoh

from ebrl.bus import BusOptions, codec, keys, zenoh_config


def format_message(key: str, msg: dict) -> str:
    if "metrics" in msg:
        metrics = " ".join(f"{k}={v:.4g}" for k, v in sorted(msg["metrics"].items()))
        return f"{key} #{msg.get('seq')} {metrics}"
    return f"{key} {json.dumps(msg, default=str)}"


def watch(connect: str, run: str | None, spans: bool = False, count: int = 0) -> int:
    """Print stats (and spans) until Ctrl-C or ``count`` messages."""
    selector = keys.stats() if run is None else keys.stats_all(run)
    inbox: queue.Queue = queue.Queue(maxsize=10_000)
    signal.signal(signal.SIGINT, lambda *_: inbox.put(None))
    conf = zenoh_config(BusOptions(mode="peer", connect=[connect], listen=[]))
    with zenoh.open(conf) as session:

        def on_sample(sample: zenoh.Sample) -> None:
            key = str(sample.key_expr)
            if not spans and "/spans/" in key:
                return
            try:
                inbox.put_nowait((key, codec.decode(sample.payload.to_bytes())))
            except (codec.DecodeError, queue.Full) as exc:
                print(f"{key}: dropped ({exc})")

        session.declare_subscriber(selector, on_sample)
        seen = 0
        while count == 0 or seen < count:
            item = inbox.get()
            if item is None:
                break
            print(format_message(*item), flush=True)
            seen += 1
    return 0
