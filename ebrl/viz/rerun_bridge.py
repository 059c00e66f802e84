"""Spans, stats and events from the bus -> a rerun recording with a live Gantt and plots.

The only module that imports rerun-sdk (used by the viz service alone).

* **Gantt.** A span becomes a bar in a ``StateTimelineView``: ``StateChange``
  with the span's state at its start and ``""`` (a gap) at its end, on the
  ``wall`` timeline (epoch seconds). Lanes are entities under ``timeline/``,
  prefixed so that alphabetical order is pipeline order (``1_sim/g00``,
  ``2_gen``, ``3_train``, ``4_weights``, ``5_alloc``). Spans that overlap on one
  lane would cut each other off, so they are packed into sub-lanes
  (``2_gen_1``, ...). Spans are buffered and sent as columns (``send_columns``)
  every ``flush_s``: one call per lane instead of two ``log`` calls per span.
* **Colours mean something**: the state is the kind of work (``chunk``,
  ``wait``, ``forward``, ``update``, ``publish``, ``realloc``), coloured by a
  static ``StateConfiguration`` per lane; a weights span ``v<n>`` is a
  ``publish`` bar and a line in the event log.
* **Plots** (``plots/<topic>/...``): the stats metrics a user looks at, one
  ``TimeSeriesView`` per topic; every other metric is kept under
  ``metrics/<service><instance>/...``. Training losses are also on the
  ``iteration`` timeline (the policy version).
* **Events** (``events``): a ``TextLog`` of launcher, service and allocator events.
"""

from __future__ import annotations

import collections
import re
import subprocess
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


class RerunBridge:
    """Feeds one ``rr.RecordingStream``; call ``on_*`` as messages arrive and ``flush()`` periodically."""

    def __init__(self, recording: rr.RecordingStream):
        self.rec = recording
        self._pending: dict[str, list[tuple[float, str]]] = collections.defaultdict(list)  # entity -> rows
        self._sublanes: dict[str, list[float]] = {}  # lane -> end time of the last span of each sub-lane
        self._configured: set[str] = set()
        self.spans = 0
        self.reports = 0
        self.events = 0

    # --- spans ------------------------------------------------------------------------

    def on_spans(self, batch: SpanBatch) -> None:
        for span in batch.spans():
            self.on_span(span)

    def on_span(self, span: Span) -> None:
        ends = self._sublanes.setdefault(span.lane, [])
        sub = next((i for i, end in enumerate(ends) if end <= span.start), None)
        if sub is None:
            sub = len(ends)
            ends.append(span.end)
        else:
            ends[sub] = max(ends[sub], span.end)
        entity = lane_entity(span.lane, sub)
        if entity not in self._configured:
            self._configured.add(entity)
            states = list(STATE_COLORS)
            colors = np.array([STATE_COLORS[s] for s in states], np.uint32)
            self.rec.log(entity, rr.StateConfiguration(values=states, colors=colors), static=True)
        rows = self._pending[entity]
        rows.append((span.start, state_of(span)))
        rows.append((span.end, ""))
        self.spans += 1
        if span.lane == "weights":
            self._text(span.end, f"weights {span.label} published by {span.service}/{span.instance} "
                                 f"({(span.end - span.start) * 1e3:.1f} ms)", "DEBUG")

    def flush(self) -> None:
        """Send buffered span edges, one ``send_columns`` per lane entity."""
        pending, self._pending = self._pending, collections.defaultdict(list)
        for entity, rows in pending.items():
            rows.sort(key=lambda r: r[0])
            times = np.array([t for t, _ in rows], dtype=np.float64)
            states = [s for _, s in rows]
            self.rec.send_columns(entity, indexes=[rr.TimeColumn("wall", timestamp=times)],
                                  columns=rr.StateChange.columns(state=states))

    # --- stats ------------------------------------------------------------------------

    def on_stats(self, report: StatsReport) -> None:
        self.reports += 1
        who = f"{report.service}{report.instance}"
        iteration = report.metrics.get("train/policy_version")
        losses = []
        self.rec.reset_time()
        self.rec.set_time("wall", timestamp=report.time)
        for metric, value in report.metrics.items():
            if not np.isfinite(value):
                continue
            topic = topic_of(metric)
            if topic is None:
                entity = f"metrics/{who}/{metric}"
            elif topic in ("busy", "quota", "cpu"):
                entity = f"plots/{topic}/{who}/{metric.split('/', 1)[1]}"
            else:
                entity = f"plots/{topic}/{who}/{metric.replace('/', '.')}"
            if topic == "losses":
                losses.append((entity, value))
            else:
                self.rec.log(entity, rr.Scalars(float(value)))
        if losses and iteration is not None:  # losses also on the iteration timeline
            self.rec.set_time("iteration", sequence=int(iteration))
        for entity, value in losses:
            self.rec.log(entity, rr.Scalars(float(value)))

    # --- events -----------------------------------------------------------------------

    def on_event(self, event: Event) -> None:
        self.events += 1
        level = "WARN" if event.kind in ("exited", "restart", "failure") else "INFO"
        self._text(event.time, f"[{event.service}/{event.instance}] {event.kind}: {event.text}", level)

    def _text(self, when: float, text: str, level: str) -> None:
        self.rec.reset_time()
        self.rec.set_time("wall", timestamp=when)
        self.rec.log("events", rr.TextLog(text, level=level))



def make_blueprint(window_s: float = 20.0) -> rrb.Blueprint:
    """Gantt and event log on the left, one plot per topic on the right; the time panel follows
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
        rrb.TimePanel(timeline="wall", play_state="following"),
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
                   blueprint: rrb.Blueprint, web_port: int = 9090) -> tuple[rr.RecordingStream, str]:
    """A recording streaming to the sinks of ``[viz] rerun`` (always also to ``rrd_path``).

    ``save``: the file only. ``serve``: a gRPC server on 127.0.0.1:``port`` that keeps up to
    ``memory_limit`` of the run, so a viewer that connects late still sees it all. ``spawn``:
    stream to the viewer listening on ``port``, starting one if none is; without a display
    (and no viewer already there) this falls back to ``save``. ``web``: stream to the server
    :func:`serve_web` started on ``port``, whose web viewer is on ``web_port``.
    Returns the recording and a line telling the user where to look.
    """
    import os
    import sys

    rec = rr.RecordingStream("ebrl", recording_id=run_name)
    sinks: list[Any] = [rr.FileSink(rrd_path)]
    where = f"saving {rrd_path} (open it with: rerun {rrd_path})"
    url = f"rerun+http://127.0.0.1:{port}/proxy"
    if mode == "spawn" and _listening(port):
        sinks.append(rr.GrpcSink(url))
        where = f"streaming to the viewer already listening on {url}; also " + where
    elif mode == "spawn" and not (os.environ.get("DISPLAY") or os.environ.get("WAYLAND_DISPLAY")):
        where = "no display (DISPLAY/WAYLAND_DISPLAY unset), so no viewer was spawned; " + where
    elif mode == "spawn":
        exe = os.path.join(os.path.dirname(sys.executable), "rerun")  # the venv's viewer, PATH or not
        rr.spawn(port=port, connect=False, server_memory_limit=memory_limit, hide_welcome_screen=True,
                 executable_path=exe if os.path.exists(exe) else None)
        sinks.append(rr.GrpcSink(url))
        where = f"viewer spawned on {url}; also " + where
    elif mode == "web":
        sinks.append(rr.GrpcSink(url))
        where = (f"web viewer on {web_url(port, web_port)} (from another machine: ssh -L {web_port}:127.0.0.1:"
                 f"{web_port} -L {port}:127.0.0.1:{port} HOST, then open that address); also " + where)
    elif mode == "serve":
        server = rr.GrpcServerSink("127.0.0.1", port, server_memory_limit=memory_limit)
        sinks.append(server)
        where = f"serving on {server.uri} (connect a viewer: rerun --connect {server.uri}); also " + where
    rec.set_sinks(*sinks, default_blueprint=blueprint)
    rec.send_blueprint(blueprint)
    return rec, where
