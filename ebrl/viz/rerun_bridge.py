"""Spans, stats and events from the bus -> a rerun recording with a live Gantt and plots.

The only module that imports rerun-sdk (used by the viz service alone).

* **Gantt.** A span becomes a bar in a ``StateTimelineView``: ``StateChange``
  with the span's state at its start and ``""`` (a gap) at its end, on the
  ``wall`` timeline (epoch seconds); back-to-back spans of a lane (a gap under
  :data:`GAP_S`) share one row. Lanes are entities under ``timeline/``,
  prefixed so that alphabetical order is pipeline order (``1_sim/g00``,
  ``2_gen``, ``3_train``, ``4_weights``, ``5_alloc``). Spans that overlap on one
  lane would cut each other off, so they are packed into sub-lanes
  (``2_gen_1``, ...).
* **Columns.** Rows are buffered per entity and sent as columns (``send_columns``),
  to each :class:`Outlet` at its own pace: a live viewer often, the file
  ``RUN_DIR/timeline.rrd`` in few large chunks (a chunk's framing costs more
  than a few rows: one ``log`` call per metric made the quickstart's file grow
  at about 240 KiB/s and a web viewer fall minutes behind).
* **Colours mean something**: the state is the kind of work (``chunk``,
  ``wait``, ``forward``, ``update``, ``publish``, ``realloc``), coloured by a
  static ``StateConfiguration`` per lane; a weights span ``v<n>`` is a
  ``publish`` bar and a line in the event log.
* **Plots** (``plots/<topic>``): the stats metrics a user looks at, one entity
  and one ``TimeSeriesView`` per topic, a series per service instance and metric
  (``sim0/sim.env_steps_per_s``); every other metric is kept under
  ``metrics/<service><instance>/<first name chunk>``. Training losses are also on
  the ``iteration`` timeline (the policy version).
* **Events** (``events``): a ``TextLog`` of launcher, service and allocator events.
"""

from __future__ import annotations

import collections
import re
import subprocess
import time
from typing import Any

import numpy as np
import rerun as rr
import rerun.blueprint as rrb

from ebrl.messages import Event, Span, SpanBatch, StatsReport
from ebrl.viz import web_url
from ebrl.viz.timeline import STAGE_ORDER, STATE_COLORS, state_of

# topic -> (view title, metric names or prefixes ending in "/")
TOPICS: dict[str, tuple[str, tuple[str, ...]]] = {
    "traj_per_s": ("trajectories/s", ("sim/segments_per_s",)),
    "env_steps_per_s": ("env steps/s", ("sim/env_steps_per_s",)),
    "policy_version": ("policy version", ("gen/policy_version", "train/policy_version")),
    "staleness": ("staleness (versions)", ("train/staleness_mean", "train/staleness_max")),
    "busy": ("busy fraction per lane (from spans)", ("busy/",)),
    "cpu": ("CPU utilisation per core (%)", ("cpu/",)),
    "gpu_sm": ("GPU SM utilisation (%)", ("gpu_sm",)),
    "gpu_mem": ("GPU memory used (MiB)", ("gpu_mem",)),
    "queues": ("queue depths", ("gen/obs_queue", "gen/obs_waiting_for_policy", "train/pending_steps")),
    "chunk_latency": ("action-chunk latency (ms)", ("sim/chunk_latency_p50_ms", "sim/chunk_latency_p99_ms")),
    "quota": ("quotas: cores and threads per service", ("quota/",)),
    "return": ("mean return (last 20 episodes)", ("sim/episode_return_mean",)),
    "success": ("success rate", ("sim/success_rate",)),
    "losses": ("training losses", ("train/policy_loss", "train/value_loss", "train/entropy", "train/approx_kl")),
}
_GPU = re.compile(r"^gpu/(\d+)_(sm_percent|mem_used_mb)$")


def lane_entity(lane: str, sub: int = 0) -> str:
    """``sim.g3`` -> ``timeline/1_sim/g03``; ``gen`` -> ``timeline/2_gen``; sub-lane n -> ``..._n``."""
    stage, _, rest = lane.partition(".")
    rank = STAGE_ORDER.index(stage) + 1 if stage in STAGE_ORDER else 9
    rest = re.sub(r"\d+", lambda m: m.group(0).zfill(2), rest)
    path = f"timeline/{rank}_{stage}" + (f"/{rest}" if rest else "")
    return path + (f"_{sub}" if sub else "")


def topic_of(metric: str) -> str | None:
    gpu = _GPU.match(metric)
    if gpu:
        return "gpu_sm" if gpu.group(2) == "sm_percent" else "gpu_mem"
    for topic, (_, names) in TOPICS.items():
        for name in names:
            if metric == name or (name.endswith("/") and metric.startswith(name)):
                return topic
    return None


class Outlet:
    """One recording stream and how often each family of entities is sent to it.

    Rows are buffered per entity and sent as columns (``send_columns``): one chunk per entity per send. A
    chunk costs about 1.1 KiB in a recording beyond its rows (its schema, ids, framing), and a viewer pays per
    chunk too, so how often each family is sent decides both the file's growth and whether a viewer keeps up:
    row by row, the quickstart made 186 chunks/s, about 240 KiB/s of ``timeline.rrd``, and the web viewer fell
    minutes behind (BENCHMARKS.md, "The live view")."""

    def __init__(self, rec: rr.RecordingStream, every_s: dict[str, float]):
        self.rec = rec
        self.every_s = every_s  # family -> seconds between sends (FAMILIES)
        self._rows: dict[str, dict[str, list[tuple]]] = {f: collections.defaultdict(list) for f in FAMILIES}
        self._sent = dict.fromkeys(FAMILIES, -np.inf)
        self._static: dict[str, Any] = {}  # entity -> the key of what was logged static on it
        self.chunks = 0  # chunks sent (for benchmarks)

    def add(self, family: str, entity: str, row: tuple) -> None:
        self._rows[family][entity].append(row)

    def static(self, entity: str, archetype, key: Any = True) -> None:
        """Log ``archetype`` static on ``entity`` (a lane's colours, a series' names) unless what was logged there
        has this ``key`` already (a new key: logged again, replacing it)."""
        if self._static.get(entity) != key:
            self._static[entity] = key
            self.rec.log(entity, archetype, static=True)

    def flush(self, now: float, force: bool = False) -> None:
        """Send every family whose interval has passed since it was last sent (every family with ``force``)."""
        for family in FAMILIES:
            if force or now - self._sent[family] >= self.every_s[family]:
                self._sent[family] = now
                rows, self._rows[family] = self._rows[family], collections.defaultdict(list)
                for entity, entity_rows in rows.items():
                    self._send(family, entity, sorted(entity_rows, key=lambda r: r[0]))

    def _send(self, family: str, entity: str, rows: list[tuple]) -> None:
        if family == "timeline":  # rows: (time, state)
            self._columns(entity, rows, rr.StateChange.columns(state=[r[1] for r in rows]))
        elif family == "events":  # rows: (time, text, level)
            self._columns(entity, rows, rr.TextLog.columns(text=[r[1] for r in rows], level=[r[2] for r in rows]))
        else:  # plots, metrics: (time, values, iteration or None); with an iteration also on that timeline
            for part in ([r for r in rows if r[2] is not None], [r for r in rows if r[2] is None]):
                if part:
                    values = rr.Scalars.columns(scalars=np.array([v for r in part for v in r[1]], np.float64))
                    iteration = None if part[0][2] is None else [r[2] for r in part]
                    self._columns(entity, part, values.partition([len(r[1]) for r in part]), iteration)

    def _columns(self, entity: str, rows: list[tuple], columns, iteration: list[int] | None = None) -> None:
        """One chunk: ``rows``' times (their first field) on ``wall`` (and ``iteration``) with ``columns``."""
        indexes = [rr.TimeColumn("wall", timestamp=np.array([r[0] for r in rows], dtype=np.float64))]
        if iteration is not None:
            indexes.append(rr.TimeColumn("iteration", sequence=np.array(iteration, np.int64)))
        self.rec.send_columns(entity, indexes=indexes, columns=columns)
        self.chunks += 1


FAMILIES = ("timeline", "plots", "metrics", "events")
# A live viewer: the Gantt every second, the plots every 2 s, the metrics no view shows every 30 s: about 10 chunks
# a second on the quickstart. Twice as often (20 chunks/s), a web viewer sharing 2 cores with the run and a native
# viewer fell minutes behind in 10 minutes; at this pace it stayed within 1.6 s (median; BENCHMARKS.md).
LIVE_EVERY_S = {"timeline": 1.0, "plots": 2.0, "metrics": 30.0, "events": 2.0}
# The file (RUN_DIR/timeline.rrd): few, large chunks; what a kill -9 of viz loses is in RUN_DIR/stats.msgpack.
FILE_EVERY_S = dict.fromkeys(FAMILIES, 60.0)
# Back-to-back spans of one lane: a gap below this is not drawn (a group's chunk and wait spans are 0.15 ms apart
# at the median on the quickstart, 1.5 ms at p99); one row per span instead of two. RUN_DIR/stats.msgpack keeps them.
GAP_S = 0.002
# An idle lane's last span is closed this long after its end (a following span would have arrived by then).
HOLD_S = 1.0


class RerunBridge:
    """Spans, stats and events -> rows of entities (see the module's docstring), sent to each outlet as columns;
    call ``on_*`` as messages arrive and :meth:`flush` often (each outlet sends at its own pace)."""

    def __init__(self, *outlets: Outlet):
        self.outlets = outlets
        self._ends: dict[str, list[float]] = {}  # lane -> end time of the last span of each sub-lane
        self._open: dict[str, float] = {}  # entity -> end of its last span, not yet sent as a gap
        self._latest: dict[str, dict[str, float]] = {}  # stats entity -> series -> its latest value
        self.spans = 0
        self.reports = 0
        self.events = 0

    def _add(self, family: str, entity: str, row: tuple) -> None:
        for outlet in self.outlets:
            outlet.add(family, entity, row)

    # --- spans ------------------------------------------------------------------------

    def on_spans(self, batch: SpanBatch) -> None:
        for span in batch.spans():
            self.on_span(span)

    def on_span(self, span: Span) -> None:
        ends = self._ends.setdefault(span.lane, [])
        sub = next((i for i, end in enumerate(ends) if end <= span.start), None)
        if sub is None:
            sub = len(ends)
            ends.append(span.end)
        else:
            ends[sub] = max(ends[sub], span.end)
        entity = lane_entity(span.lane, sub)
        states = list(STATE_COLORS)
        for outlet in self.outlets:
            outlet.static(entity, rr.StateConfiguration(values=states, colors=np.array(
                [STATE_COLORS[s] for s in states], np.uint32)))
        last_end = self._open.pop(entity, None)
        if last_end is not None and span.start - last_end > GAP_S:
            self._add("timeline", entity, (last_end, ""))
        self._add("timeline", entity, (span.start, state_of(span)))
        self._open[entity] = span.end
        self.spans += 1
        if span.lane == "weights":
            self._text(span.end, f"weights {span.label} published by {span.service}/{span.instance} "
                                 f"({(span.end - span.start) * 1e3:.1f} ms)", "DEBUG")

    def flush(self, now: float | None = None, force: bool = False) -> None:
        """Close the lanes idle for :data:`HOLD_S` (every lane with ``force``, as the run ends), then let each
        outlet send what is due (``now``: epoch seconds, default the clock)."""
        now = time.time() if now is None else now
        for entity, end in list(self._open.items()):
            if force or now - end > HOLD_S:
                del self._open[entity]
                self._add("timeline", entity, (end, ""))
        for outlet in self.outlets:
            outlet.flush(now, force)

    # --- stats ------------------------------------------------------------------------

    def on_stats(self, report: StatsReport) -> None:
        """A report becomes one row on each of its entities: ``plots/<topic>`` (one series per service instance
        and metric: ``sim0/sim.env_steps_per_s``) and ``metrics/<service><instance>/<family>`` (the metrics no
        plot shows, by their first name chunk: ``metrics/train0/train``). An entity's row holds every series it
        has had, the others' latest values with the reporter's new ones (a service that stopped reporting a
        metric keeps its last value)."""
        self.reports += 1
        who = f"{report.service}{report.instance}"
        version = report.metrics.get("train/policy_version")
        iteration = int(version) if version is not None and np.isfinite(version) else None
        fresh: dict[str, dict[str, float]] = collections.defaultdict(dict)  # entity -> series -> value
        for metric, value in report.metrics.items():
            if not np.isfinite(value):
                continue
            topic = topic_of(metric)
            if topic is None:
                family, _, name = metric.partition("/")
                fresh[f"metrics/{who}/{family}"][name or family] = float(value)
            elif topic in ("busy", "quota", "cpu"):
                fresh[f"plots/{topic}"][f"{who}/{metric.split('/', 1)[1]}"] = float(value)
            else:
                fresh[f"plots/{topic}"][f"{who}/{metric.replace('/', '.')}"] = float(value)
        for entity, values in fresh.items():
            latest = self._latest.setdefault(entity, {})
            latest.update(values)  # a new series joins at the end: the others keep their places
            names = list(latest)
            for outlet in self.outlets:
                outlet.static(entity, rr.SeriesLines(names=names), key=len(names))
            family = "plots" if entity.startswith("plots/") else "metrics"
            # training losses also on the iteration timeline (the policy version)
            self._add(family, entity, (report.time, list(latest.values()),
                                       iteration if entity == "plots/losses" else None))

    # --- events -----------------------------------------------------------------------

    def on_event(self, event: Event) -> None:
        self.events += 1
        level = "WARN" if event.kind in ("exited", "restart", "failure") else "INFO"
        self._text(event.time, f"[{event.service}/{event.instance}] {event.kind}: {event.text}", level)

    def _text(self, when: float, text: str, level: str) -> None:
        self._add("events", "events", (when, text, level))


def make_blueprint(window_s: float = 20.0) -> rrb.Blueprint:
    """Gantt and event log on the left, one plot per topic on the right; the time panel (collapsed) follows
    the present on the ``wall`` timeline and every view shows the last ``window_s`` seconds."""
    follow = rrb.TimeAxis(view_range=rrb.TimeRange(
        start=rrb.TimeRangeBoundary.cursor_relative(seconds=-window_s),
        end=rrb.TimeRangeBoundary.cursor_relative(seconds=1.0)))
    plots = [rrb.TimeSeriesView(origin=f"plots/{topic}", name=title, axis_x=follow)
             for topic, (title, _) in TOPICS.items()]
    return rrb.Blueprint(
        rrb.Horizontal(
            rrb.Vertical(
                rrb.StateTimelineView(origin="timeline", name="Gantt: busy spans per lane", time_view=follow),
                rrb.TextLogView(origin="events", name="events"),
                row_shares=[3, 1],
            ),
            rrb.Grid(*plots, grid_columns=3),
            column_shares=[1, 1],
        ),
        # collapsed: its streams' density graph over the whole run is redrawn every frame, a cost that grows with
        # the run's length (a web viewer on a loaded machine fell behind with it open; one click opens it)
        rrb.TimePanel(state="collapsed", timeline="wall", play_state="following"),
        rrb.BlueprintPanel(state="collapsed"),
        rrb.SelectionPanel(state="collapsed"),
    )


def without_analytics(run_dir: str) -> dict[str, str]:
    """Environment variables under which rerun (this SDK, its CLI and a viewer it spawns) keeps its usage
    analytics off: by default it sends them to rerun's servers, set in ``~/.config/rerun/analytics.json``. Its
    config and data directories become ``RUN_DIR/rerun/`` (XDG), holding a config with analytics disabled, so
    a run neither phones home nor changes the user's own rerun settings."""
    import json
    import os

    config, data = os.path.join(run_dir, "rerun", "config"), os.path.join(run_dir, "rerun", "data")
    path = os.path.join(config, "rerun", "analytics.json")
    os.makedirs(os.path.dirname(path), mode=0o700, exist_ok=True)
    os.makedirs(os.path.join(data, "rerun", "analytics"), mode=0o700, exist_ok=True)
    with open(path, "w") as fh:
        json.dump({"analytics_enabled": False, "analytics_id": "", "metadata": {}, "config_file_path": path,
                   "data_dir_path": os.path.join(data, "rerun", "analytics")}, fh)
    return {"XDG_CONFIG_HOME": config, "XDG_DATA_HOME": data}


def _listening(port: int) -> bool:
    import socket

    with socket.socket() as sock:
        sock.settimeout(0.2)
        return sock.connect_ex(("127.0.0.1", port)) == 0


def serve_web(port: int, web_port: int, memory_limit: str, timeout: float = 60.0) -> subprocess.Popen:
    """Start the rerun CLI bundled with rerun-sdk as the web viewer's server: its gRPC server on
    127.0.0.1:``port`` (keeping up to ``memory_limit`` of the run for pages opened late) and the web viewer's
    page over HTTP on 127.0.0.1:``web_port``. Both on loopback (``--bind``): the SDK's own
    ``serve_web_viewer`` listens on every interface. The process gets SIGTERM when this thread's process dies
    (``PR_SET_PDEATHSIG``: call it from the main thread); stop it with :func:`stop_web`."""
    import ctypes
    import os
    import signal
    import time

    for p in (port, web_port):
        if _listening(p):
            raise RuntimeError(f"viz.rerun = web: port {p} on 127.0.0.1 is taken (set viz.port / viz.web_port)")
    import rerun_cli

    # the binary itself, not the `rerun` script that runs it as a child (which would outlive a SIGKILLed viz)
    exe = os.path.join(os.path.dirname(rerun_cli.__file__), "rerun")
    cmd = [exe if os.path.exists(exe) else "rerun", "--serve-web", "--bind", "127.0.0.1", "--port", str(port),
           "--web-viewer-port", str(web_port), "--server-memory-limit", memory_limit]
    proc = subprocess.Popen(cmd, stdin=subprocess.DEVNULL,
                            preexec_fn=lambda: ctypes.CDLL("libc.so.6").prctl(1, signal.SIGTERM))
    deadline = time.monotonic() + timeout
    while not (_listening(port) and _listening(web_port)):
        if proc.poll() is not None or time.monotonic() > deadline:
            stop_web(proc)
            raise RuntimeError(f"the rerun web viewer ({' '.join(cmd)}) did not start listening on ports "
                               f"{port} and {web_port} within {timeout:.0f} s (exit code {proc.returncode})")
        time.sleep(0.1)
    return proc


def stop_web(proc: subprocess.Popen) -> None:
    proc.terminate()
    try:
        proc.wait(10)
    except subprocess.TimeoutExpired:
        proc.kill()
        proc.wait()


def describe_recording(path: str) -> dict[str, Any]:
    """Entity paths of a saved ``.rrd`` with their row counts (for tests and ``ebrl report``)."""
    from rerun.chunk import RrdReader

    counts: dict[str, int] = collections.Counter()
    for chunk in RrdReader(path).stream():
        counts[str(chunk.entity_path)] += chunk.num_rows
    return dict(counts)


def open_recording(mode: str, rrd_path: str, run_name: str, port: int, memory_limit: str,
                   blueprint: rrb.Blueprint, web_port: int = 9090) -> tuple[list[Outlet], str]:
    """The outlets of ``[viz] rerun``: always the file ``rrd_path``; in every mode but ``save`` also a live
    stream, each one recording stream of the run (one recording id, so the file and the live view are the same
    recording). The live one is sent to at :data:`LIVE_EVERY_S`, the file at :data:`FILE_EVERY_S`.

    ``save``: the file only. ``serve``: a gRPC server on 127.0.0.1:``port`` that keeps up to
    ``memory_limit`` of the run, so a viewer that connects late still sees it all. ``spawn``:
    stream to the viewer listening on ``port``, starting one if none is; without a display
    (and no viewer already there) this falls back to ``save``. ``web``: stream to the server
    :func:`serve_web` started on ``port``, whose web viewer is on ``web_port``.
    Returns the outlets (the live one first) and a line telling the user where to look.
    """
    import os
    import sys

    def stream(*sinks) -> rr.RecordingStream:
        rec = rr.RecordingStream("ebrl", recording_id=run_name)
        rec.set_sinks(*sinks, default_blueprint=blueprint)
        rec.send_blueprint(blueprint)
        return rec

    live: Any = None
    where = f"saving {rrd_path} (open it with: rerun {rrd_path})"
    url = f"rerun+http://127.0.0.1:{port}/proxy"
    if mode == "spawn" and _listening(port):
        live = rr.GrpcSink(url)
        where = f"streaming to the viewer already listening on {url}; also " + where
    elif mode == "spawn" and not (os.environ.get("DISPLAY") or os.environ.get("WAYLAND_DISPLAY")):
        where = "no display (DISPLAY/WAYLAND_DISPLAY unset), so no viewer was spawned; " + where
    elif mode == "spawn":
        exe = os.path.join(os.path.dirname(sys.executable), "rerun")  # the venv's viewer, PATH or not
        rr.spawn(port=port, connect=False, server_memory_limit=memory_limit, hide_welcome_screen=True,
                 executable_path=exe if os.path.exists(exe) else None)
        live = rr.GrpcSink(url)
        where = f"viewer spawned on {url}; also " + where
    elif mode == "web":
        live = rr.GrpcSink(url)
        where = (f"web viewer on {web_url(port, web_port)} (from another machine: ssh -L {web_port}:127.0.0.1:"
                 f"{web_port} -L {port}:127.0.0.1:{port} HOST, then open that address); also " + where)
    elif mode == "serve":
        live = rr.GrpcServerSink("127.0.0.1", port, server_memory_limit=memory_limit)
        where = f"serving on {live.uri} (connect a viewer: rerun --connect {live.uri}); also " + where
    outlets = [Outlet(stream(live), LIVE_EVERY_S)] if live is not None else []
    outlets.append(Outlet(stream(rr.FileSink(rrd_path)), FILE_EVERY_S))
    return outlets, where
