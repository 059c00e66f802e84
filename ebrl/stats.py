"""Watching a run from a script: :func:`observer_config` (a Zenoh config signed in as an observer), and
``ebrl stats``, which subscribes to ``ebrl/stats/**`` and prints every decoded message."""

from __future__ import annotations

import json
import queue
import signal
import os
import sys
from pathlib import Path

import zenoh

from ebrl.bus import auth, codec, keys
from ebrl.bus.session import BusOptions, zenoh_config

DEFAULT_ENDPOINT = "tcp/127.0.0.1:7447"


def observer_config(run: str | os.PathLike, connect: str | None = None):
    """A ``zenoh.Config`` that watches the run in directory ``run`` (or whose secret file ``run`` is): signs in
    as observer and connects to the run's launcher (from ``RUN_DIR/bus.json`` unless ``connect`` is given).
    ``zenoh.open(observer_config("runs/quickstart-..."))`` then subscribe to ``ebrl/stats/**``."""
    run = Path(run)
    secret = run if run.is_file() else run / auth.FILENAME
    signed = secret.exists() or run.is_file()  # a run with bus.auth = false has no secret: an open bus
    if connect is None:
        try:
            connect = json.loads((secret.parent / "bus.json").read_text())["listen"][0]
        except (OSError, ValueError, KeyError, IndexError):
            connect = DEFAULT_ENDPOINT
    return zenoh_config(BusOptions(mode="client", connect=[connect], listen=[],
                                   secret_file=str(secret) if signed else "", role="observer"))


def format_message(key: str, msg: dict) -> str:
    if "metrics" in msg:
        metrics = " ".join(f"{k}={v:.4g}" for k, v in sorted(msg["metrics"].items()))
        return f"{key} #{msg.get('seq')} {metrics}"
    return f"{key} {json.dumps(msg, default=str)}"


def watch(connect: str | None, run: str | None, spans: bool = False, count: int = 0, secret: str = "") -> int:
    """Print stats (and spans) until Ctrl-C or ``count`` messages. ``secret``: the run's secret file (or its
    directory), signing in as an observer; empty for a run with ``bus.auth = false``. ``connect`` None: the
    endpoint in the run directory's ``bus.json``, else the default port."""
    selector = keys.stats() if run is None else keys.stats_all(run)
    inbox: queue.Queue = queue.Queue(maxsize=10_000)
    signal.signal(signal.SIGINT, lambda *_: inbox.put(None))
    try:
        if secret:
            conf = observer_config(secret, connect)
        else:
            conf = zenoh_config(BusOptions(mode="client", connect=[connect or DEFAULT_ENDPOINT], listen=[]))
    except auth.AuthError as exc:
        print(f"ebrl stats: {exc}", file=sys.stderr)
        return 2
    try:
        session = zenoh.open(conf)
    except zenoh.ZError as exc:
        where = json.loads(conf.get_json("connect/endpoints"))
        print(f"ebrl stats: cannot join a run at {', '.join(where)}: is it running, and (bus.auth, the default) "
              f"did you give its directory, `ebrl stats RUN_DIR`? ({exc})", file=sys.stderr)
        return 1
    with session:

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
