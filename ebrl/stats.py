"""Watching a run from a script: :func:`stream` (``ebrl.watch``: the run's stats reports as they arrive, until
it ends), :func:`observer_config` (a Zenoh config signed in as an observer, for a script of your own), and
``ebrl stats``, which subscribes to ``ebrl/stats/**`` and prints every decoded message (``--json``: one JSON
object per line, for other tools)."""

from __future__ import annotations

import contextlib
import json
import os
import queue
import signal
import sys
import threading
import time
from pathlib import Path
from typing import Callable, Iterator

import zenoh

from ebrl import codec, graph
from ebrl.bus import auth
from ebrl.bus.session import BusOptions, zenoh_config
from ebrl.messages import EpisodeBatch, Event, MessageError, SpanBatch, StatsReport, decode_stats_sample

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


def stream(run_dir: str | os.PathLike, *, connect: str | None = None, everything: bool = False,
           idle_timeout: float | None = None) -> Iterator[StatsReport | SpanBatch | Event | EpisodeBatch]:
    """The stats reports of the run in ``run_dir`` as they arrive (decoded, validated: what fails is skipped),
    signed in as an observer (read only). ``everything``: its spans, events and episode batches too. It ends
    once the run's launcher has left the bus (the run ended), or after ``idle_timeout`` seconds without a
    message; break out of the loop to stop earlier::

        for report in ebrl.watch("runs/quickstart-20261126-101500"):
            print(report.service, report.metrics.get("train/policy_version"))
    """
    run = run_of(run_dir)
    inbox: queue.Queue = queue.Queue(maxsize=10_000)
    ended = threading.Event()  # the run ended (its last reports came before its launchers left)

    def on_sample(sample: zenoh.Sample) -> None:
        try:
            message = decode_stats_sample(str(sample.key_expr), sample.payload.to_bytes())
        except MessageError:
            return
        if everything or isinstance(message, StatsReport):
            try:
                inbox.put_nowait(message)
            except queue.Full:  # the reader fell behind: dropped
                pass

    with zenoh.open(observer_config(run_dir, connect)) as session:
        session.declare_subscriber(graph.keys_of(run, "observer").sub("stats"), on_sample)
        when_launchers_leave(session, run, ended.set)
        last = time.monotonic()
        while True:
            try:
                message = inbox.get(timeout=0.5)
            except queue.Empty:
                if ended.is_set() or (idle_timeout is not None and time.monotonic() - last > idle_timeout):
                    return
                continue
            last = time.monotonic()
            yield message


def format_message(key: str, msg: dict) -> str:
    if "metrics" in msg:
        metrics = " ".join(f"{k}={v:.4g}" for k, v in sorted(msg["metrics"].items()))
        return f"{key} #{msg.get('seq')} {metrics}"
    return f"{key} {json.dumps(msg, default=str)}"


def command(connect: str | None, run: str | None, spans: bool = False, count: int = 0, secret: str = "",
            as_json: bool = False) -> int:
    """``ebrl stats``: print stats (and spans) until the run ends, Ctrl-C or ``count`` messages; ``as_json``: each
    as one JSON object (its key, then its fields). ``secret``: the run's secret file (or its directory), signing
    in as an observer; empty for a run with ``bus.auth = false``. ``connect`` None: the endpoint in the run
    directory's ``bus.json``, else the default port. With one run to follow (``run``, or the run of that
    directory) it ends, exit 0, once the run's launchers have left the bus, as :func:`stream` does; with every
    run, at Ctrl-C."""
    if run is None and secret:  # the run of that directory (or of the directory of that secret file)
        where = Path(secret)
        with contextlib.suppress(FileNotFoundError):
            run = run_of(where if where.is_dir() else where.parent)
    selector = graph.keys_of(run, "observer").sub("stats")  # run None: of every run
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
        if run is not None:
            when_launchers_leave(session, run, lambda: inbox.put(None))
        seen = 0
        while count == 0 or seen < count:
            item = inbox.get()
            if item is None:  # Ctrl-C, or the run ended (what it sent before came first)
                break
            key, msg = item
            print(json.dumps({"key": key, **msg}, default=_plain) if as_json else format_message(key, msg), flush=True)
            seen += 1
    return 0


def run_of(run_dir: str | os.PathLike) -> str:
    """The run's name, from ``RUN_DIR/bus.json``; FileNotFoundError where it is not a started run's directory."""
    try:
        return json.loads((Path(run_dir) / "bus.json").read_text())["run"]
    except (OSError, ValueError, KeyError) as exc:
        raise FileNotFoundError(f"{run_dir}: not a started run's directory (no bus.json: {exc})") from None


def when_launchers_leave(session: zenoh.Session, run: str, ended: Callable[[], None]) -> None:
    """Call ``ended()`` (on Zenoh's thread) once every launcher of ``run`` that was on the bus has left it: the
    run ended. (A subscriber with a callback lives as long as the session.)"""
    launchers: set[str] = set()

    def on_token(sample: zenoh.Sample) -> None:
        (launchers.add if sample.kind == zenoh.SampleKind.PUT else launchers.discard)(str(sample.key_expr))
        if not launchers:
            ended()

    session.liveliness().declare_subscriber(graph.keys_of(run, "observer").watch(), on_token, history=True)


def _plain(value):
    """A decoded array (numpy) or bytes as JSON."""
    if hasattr(value, "tolist"):
        return value.tolist()
    if isinstance(value, (bytes, bytearray)):
        return value.hex()
    raise TypeError(f"{type(value).__name__} is not JSON")
