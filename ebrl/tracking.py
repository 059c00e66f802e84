"""Experiment tracking: the run's stats, episode records and eval results, keyed by env steps, into TensorBoard,
CSV and Weights & Biases.

Where it runs, and why there: in the ``log`` service (``ebrl/services/log.py``), a subscriber of
``ebrl/stats/<run>/**`` started and supervised by the launcher like ``viz``. Everything a sink needs is
already on the bus (stats reports, ``EpisodeBatch`` records, the eval service's reports), so no training
service knows the sinks exist, and a sink that stalls (a slow disk, W&B's network) or dies is isolated in its
own process: the service's inbox drops the oldest samples when it falls behind (``log/dropped``), and the
launcher restarts it or lets the run go on without it (an *optional* service). The launcher itself, which
also reads the stats, is not the place: a stalled sink there would stall the progress line and the run's
control. The logic is here, pure and testable without a bus: :class:`Tracker` turns messages into points
``(key, value, step, wall_time)`` and hands them to the sinks; a value that is not finite is dropped and
counted, and a sink that keeps failing is closed while the others go on.

The step of every point is the run's **env steps**: the sum over simulator instances of their
``sim/env_steps`` counters (a simulator that restarted counts on from where it was; a resumed run from
``meta.json``'s ``env_steps_before``). Tags are the metric names (``train/policy_loss``; a metric outside its
service's namespace gets the service in front, ``gen/proc/rss_mb``; an instance other than 0 adds
``/<instance>``), plus ``episode/return``, ``episode/length`` and ``episode/success`` once per
episode (from ``EpisodeBatch``), and ``run/env_steps``. An eval report (``eval/*``) is placed at the env
steps at which its ``eval/version`` was published, so its curve lines up with the training curves.
"""

from __future__ import annotations

import csv
import fnmatch
import json
import logging
import math
import time
from dataclasses import dataclass
from pathlib import Path
from typing import Any, Iterable, Protocol

from ebrl import config as config_mod
from ebrl.messages import EpisodeBatch, Event, SpanBatch, StatsReport

log = logging.getLogger("ebrl.tracking")

TB_DIR = "tb"
CSV_FILE = "metrics.csv"
WANDB_DIR = "wandb"
CSV_HEADER = ("step", "wall_time", "key", "value")
SINK_FAILURES_MAX = 10  # consecutive failed writes after which a sink is closed (the others go on)
# the curves the TensorBoard HPARAMS dashboard shows beside the config
HPARAM_METRICS = ("sim/episode_return_mean", "sim/success_rate", "eval/return", "eval/success_rate")


@dataclass(frozen=True)
class Point:
    key: str
    value: float
    step: int
    wall_time: float


class Sink(Protocol):
    name: str

    def scalars(self, points: list[Point]) -> None: ...

    def flush(self) -> None: ...

    def close(self) -> None: ...


@dataclass(frozen=True)
class RunInfo:
    """What every sink is told at start: the run, its resolved config (typed and as TOML) and ``meta.json``."""

    name: str
    run_dir: Path
    config: config_mod.Config
    config_toml: str
    meta: dict[str, Any]


def flat_config(cfg: config_mod.Config) -> dict[str, str | float | int]:
    """``{"run.seed": 1, "env.kwargs.obs": "rgb", "policy.hidden": "[64, 64]", ...}``: the config as
    hyperparameters (numbers stay numbers; booleans, lists and absent values become text)."""
    out: dict[str, str | float | int] = {}

    def walk(prefix: str, value: Any) -> None:
        if isinstance(value, dict):
            for key, item in value.items():
                walk(f"{prefix}.{key}" if prefix else str(key), item)
        elif isinstance(value, bool) or value is None:
            out[prefix] = "absent" if value is None else str(value).lower()
        elif isinstance(value, (int, float)):
            out[prefix] = value
        elif isinstance(value, str):
            out[prefix] = value
        else:
            out[prefix] = json.dumps(value)

    walk("", {k: v for k, v in cfg.to_dict().items() if k != "hosts" or v})
    return out


# --- sinks ---------------------------------------------------------------------------------------


class TensorBoardSink:
    """``RUN_DIR/tb/``: scalars, the config as hparams and as text, the metadata as text. Written with
    TensorBoard's own event-file writer and protobufs (the records ``torch.utils.tensorboard`` writes), so the
    log service does not import torch: on a small host it starts while generation and training import theirs,
    and its start-up was the CPU they waited for."""

    name = "tensorboard"

    def __init__(self, info: RunInfo, flush_s: float):
        from tensorboard.compat.proto.event_pb2 import Event
        from tensorboard.compat.proto.summary_pb2 import Summary
        from tensorboard.summary.writer.event_file_writer import EventFileWriter

        self._event, self._summary = Event, Summary
        self.writer = EventFileWriter(str(info.run_dir / TB_DIR), flush_secs=max(1, int(flush_s)))
        self.last_step: dict[str, int] = {}
        experiment, start, self._end = hparams_summaries(flat_config(info.config), HPARAM_METRICS)
        self._add(experiment)
        self._add(start)
        from tensorboard.plugins.text.summary_v2 import text_pb  # TensorBoard's own record, no TensorFlow

        self._add(text_pb("config", _code_block(info.config_toml)), step=0)
        self._add(text_pb("meta", _code_block(json.dumps(info.meta, indent=2))), step=0)

    def _add(self, summary: Any, step: int | None = None, wall_time: float | None = None) -> None:
        event = self._event(summary=summary, wall_time=time.time() if wall_time is None else wall_time)
        if step is not None:
            event.step = int(step)
        self.writer.add_event(event)

    def scalars(self, points: list[Point]) -> None:
        for p in points:
            # TensorBoard's reader drops a tag's later points when a step goes back (it takes it for a restart)
            step = max(p.step, self.last_step.get(p.key, p.step))
            self.last_step[p.key] = step
            self._add(self._summary(value=[self._summary.Value(tag=p.key, simple_value=float(p.value))]),
                      step=step, wall_time=p.wall_time)

    def flush(self) -> None:
        self.writer.flush()

    def close(self) -> None:
        self._add(self._end)
        self.writer.close()


def hparams_summaries(params: dict[str, str | float | int], metrics: Iterable[str]) -> tuple[Any, Any, Any]:
    """The HParams plugin's three records: the experiment (which hyperparameters and metrics there are), the
    session's start (this run's values) and its end (success). TensorBoard's own ``summary_v2`` writes the
    first two without TensorFlow; the end record is the plugin's data as its ``metadata`` module builds it."""
    from tensorboard.compat.proto.summary_pb2 import Summary
    from tensorboard.plugins.hparams import metadata, summary_v2
    from tensorboard.plugins.hparams.api_pb2 import Status
    from tensorboard.plugins.hparams.plugin_data_pb2 import HParamsPluginData, SessionEndInfo

    experiment = summary_v2.hparams_config_pb([summary_v2.HParam(key) for key in params],
                                              [summary_v2.Metric(m) for m in metrics])
    end = HParamsPluginData(session_end_info=SessionEndInfo(status=Status.Value("STATUS_SUCCESS")),
                            version=metadata.PLUGIN_DATA_VERSION)
    end_summary = Summary(value=[Summary.Value(tag=metadata.SESSION_END_INFO_TAG,
                                               metadata=metadata.create_summary_metadata(end))])
    return experiment, summary_v2.hparams_pb(params), end_summary


class CsvSink:
    """``RUN_DIR/metrics.csv`` in long format: ``step,wall_time,key,value``, appended (a resumed run goes on)."""

    name = "csv"

    def __init__(self, info: RunInfo):
        path = info.run_dir / CSV_FILE
        new = not path.exists() or path.stat().st_size == 0
        self.fh = open(path, "a", newline="")
        self.writer = csv.writer(self.fh)
        if new:
            self.writer.writerow(CSV_HEADER)

    def scalars(self, points: list[Point]) -> None:
        self.writer.writerows((p.step, f"{p.wall_time:.3f}", p.key, repr(p.value)) for p in points)

    def flush(self) -> None:
        self.fh.flush()

    def close(self) -> None:
        self.fh.close()


class WandbSink:
    """Weights & Biases (``log.wandb``, the optional extra): one W&B run per EBRL run (its directory name is the
    W&B run id, so a resumed run continues it), every point logged against ``env_steps``."""

    name = "wandb"

    def __init__(self, info: RunInfo, section: config_mod.LogSection):
        wandb = import_wandb()
        run_id = info.run_dir.name.replace("/", "-")
        self.run = wandb.init(
            project=section.wandb_project, entity=section.wandb_entity or None, group=section.wandb_group or None,
            tags=list(section.wandb_tags) or None, name=run_id, id=run_id, resume="allow", mode=section.wandb_mode,
            dir=str(info.run_dir), config={**info.config.to_dict(), "meta": info.meta})
        self.run.define_metric("env_steps")
        self.run.define_metric("*", step_metric="env_steps")

    def scalars(self, points: list[Point]) -> None:
        rows: dict[int, dict[str, float]] = {}
        for p in points:  # one log call per step; a key seen twice at one step keeps its last value
            rows.setdefault(p.step, {})[p.key] = p.value
        for step in sorted(rows):
            self.run.log({**rows[step], "env_steps": step})

    def flush(self) -> None:
        pass  # W&B's own process writes as it goes

    def close(self) -> None:
        self.run.finish()


class WandbMissing(RuntimeError):
    pass


def import_wandb() -> Any:
    try:
        import wandb
    except ImportError:
        raise WandbMissing("log.wandb = true needs the wandb package: pip install 'ebrl[wandb]' "
                           "(or set log.wandb = false)") from None
    return wandb


def wandb_problem(section: config_mod.LogSection) -> str | None:
    """Why ``log.wandb`` cannot work here (checked by ``ebrl up`` before anything starts); None: it can."""
    import importlib.util
    import netrc
    import os

    if not section.wandb:
        return None
    if importlib.util.find_spec("wandb") is None:
        return "log.wandb = true needs the wandb package: pip install 'ebrl[wandb]' (or set log.wandb = false)"
    if section.wandb_mode == "online" and not os.environ.get("WANDB_API_KEY"):
        try:
            logged_in = netrc.netrc(os.environ.get("NETRC")).authenticators("api.wandb.ai") is not None
        except (OSError, netrc.NetrcParseError):
            logged_in = False
        if not logged_in:
            return ("log.wandb_mode = \"online\" needs a W&B login (`wandb login`, or WANDB_API_KEY); or set "
                    "log.wandb_mode = \"offline\" (upload later with `wandb sync RUN_DIR/wandb/offline-run-*`)")
    return None


def _code_block(text: str) -> str:
    """Markdown code (TensorBoard's text dashboard renders markdown)."""
    return "\n".join("    " + line for line in text.splitlines())


def open_sinks(info: RunInfo, section: config_mod.LogSection) -> list[Sink]:
    """The sinks ``[log]`` asks for; one that cannot start is logged and left out (the others go on)."""
    wanted: list[tuple[str, Any]] = []
    if section.tensorboard:
        wanted.append(("tensorboard", lambda: TensorBoardSink(info, section.flush_s)))
    if section.csv:
        wanted.append(("csv", lambda: CsvSink(info)))
    if section.wandb:
        wanted.append(("wandb", lambda: WandbSink(info, section)))
    sinks = []
    for name, make in wanted:
        try:
            sinks.append(make())
        except Exception as exc:
            log.error("sink %s not started: %s", name, exc, exc_info=not isinstance(exc, WandbMissing))
    return sinks


# --- the tracker ---------------------------------------------------------------------------------


class Tracker:
    """Messages from ``ebrl/stats/<run>/**`` in, points to every sink out (pure apart from the sinks)."""

    def __init__(self, sinks: Iterable[Sink], exclude: Iterable[str] = (), env_steps_before: int = 0,
                 flush_s: float = 5.0):
        self.sinks = list(sinks)
        self.exclude = tuple(exclude)
        self.base = int(env_steps_before)  # env steps of the run before this launcher started (a resume)
        self.flush_s = flush_s
        self.sim_steps: dict[int, int] = {}  # sim instance -> its last sim/env_steps
        self.sim_offset: dict[int, int] = {}  # ... plus what it had counted before it restarted
        self.version_steps: dict[int, int] = {}  # policy version -> env steps when training published it
        self.failures: dict[str, int] = {}
        self.points = 0
        self.episodes = 0
        self.nonfinite_dropped = 0
        self.sink_errors = 0
        self.closed_sinks: list[str] = []
        self._excluded: dict[str, bool] = {}
        self._last_flush = time.monotonic()

    @property
    def env_steps(self) -> int:
        """The run's env steps so far, as the simulators' reports say."""
        return self.base + sum(self.sim_offset.get(i, 0) + n for i, n in self.sim_steps.items())

    # --- messages in ---

    def on_messages(self, messages: Iterable[Any]) -> None:
        points: list[Point] = []
        for msg in messages:
            if isinstance(msg, StatsReport):
                points += self.on_report(msg)
            elif isinstance(msg, EpisodeBatch):
                points += self.on_episodes(msg)
            elif not isinstance(msg, (SpanBatch, Event)):
                log.debug("not tracked: %r", type(msg).__name__)
        self.write(points)
        if time.monotonic() - self._last_flush >= self.flush_s:
            self.flush()

    def on_report(self, report: StatsReport) -> list[Point]:
        m = report.metrics
        if report.service == "sim" and "sim/env_steps" in m and _finite(m["sim/env_steps"]):
            steps = int(m["sim/env_steps"])
            last = self.sim_steps.get(report.instance, 0)
            if steps < last:  # the simulator restarted: its counter began again at 0
                self.sim_offset[report.instance] = self.sim_offset.get(report.instance, 0) + last
            self.sim_steps[report.instance] = steps
        step = self.env_steps
        if report.service == "train" and report.instance == 0 and _finite(m.get("train/policy_version", math.nan)):
            self.version_steps.setdefault(int(m["train/policy_version"]), step)
        if report.service == "eval" and _finite(m.get("eval/version", math.nan)):
            step = self.version_steps.get(int(m["eval/version"]), step)  # where that policy was made
        suffix = f"/{report.instance}" if report.instance else ""
        points = [Point(tag(report.service, name) + suffix, value, step, report.time) for name, value in m.items()
                  if not self.excluded(name)]  # a pattern may name the metric or its key (write())
        if report.service == "sim" and report.instance == 0:
            points.append(Point("run/env_steps", float(step), step, report.time))
        return points

    def on_episodes(self, batch: EpisodeBatch) -> list[Point]:
        """One point per episode and quantity, at the run's env steps when the episode ended."""
        others = self.env_steps - self.sim_offset.get(batch.instance, 0) - self.sim_steps.get(batch.instance, 0)
        offset = others + self.sim_offset.get(batch.instance, 0)
        suffix = f"/{batch.instance}" if batch.instance else ""
        points = []
        for ret, length, success, steps, end in zip(batch.returns, batch.length, batch.success, batch.env_steps,
                                                    batch.end_time):
            step = offset + steps
            points.append(Point("episode/return" + suffix, ret, step, end))
            points.append(Point("episode/length" + suffix, float(length), step, end))
            if success is not None:
                points.append(Point("episode/success" + suffix, float(success), step, end))
        self.episodes += len(batch.returns)
        return points

    # --- points out ---

    def excluded(self, key: str) -> bool:
        if key not in self._excluded:
            self._excluded[key] = any(fnmatch.fnmatchcase(key, pattern) for pattern in self.exclude)
        return self._excluded[key]

    def write(self, points: list[Point]) -> None:
        kept = []
        for p in points:
            if self.excluded(p.key):
                continue
            if not _finite(p.value):  # NaN or inf: no sink can plot it, and some refuse it
                self.nonfinite_dropped += 1
                continue
            kept.append(p)
        if not kept:
            return
        self.points += len(kept)
        self._each_sink("scalars", kept)

    def flush(self) -> None:
        self._last_flush = time.monotonic()
        self._each_sink("flush")

    def close(self) -> None:
        self._each_sink("flush")
        for sink in self.sinks:
            try:
                sink.close()
            except Exception as exc:
                log.error("sink %s did not close cleanly: %s", sink.name, exc)
        self.sinks = []

    def _each_sink(self, method: str, *args: Any) -> None:
        for sink in list(self.sinks):
            try:
                getattr(sink, method)(*args)
                self.failures[sink.name] = 0
            except Exception as exc:
                self.sink_errors += 1
                n = self.failures[sink.name] = self.failures.get(sink.name, 0) + 1
                log.error("sink %s: %s failed (%d in a row): %s", sink.name, method, n, exc, exc_info=n == 1)
                if n >= SINK_FAILURES_MAX:
                    log.error("sink %s closed after %d failures in a row; the other sinks go on", sink.name, n)
                    self.sinks.remove(sink)
                    self.closed_sinks.append(sink.name)
                    try:
                        sink.close()
                    except Exception:
                        pass

    def metrics(self) -> dict[str, float]:
        return {"log/points": float(self.points), "log/episodes": float(self.episodes),
                "log/nonfinite_dropped": float(self.nonfinite_dropped), "log/sink_errors": float(self.sink_errors),
                "log/sinks": float(len(self.sinks)), "log/env_steps": float(self.env_steps)}


class MemorySink:
    """Points kept in memory, per key (``ebrl report`` draws its learning curves from them)."""

    name = "memory"

    def __init__(self):
        self.series: dict[str, list[Point]] = {}

    def scalars(self, points: list[Point]) -> None:
        for p in points:
            self.series.setdefault(p.key, []).append(p)

    def flush(self) -> None:
        pass

    def close(self) -> None:
        pass


def curves(messages: Iterable[Any], env_steps_before: int = 0) -> dict[str, list[Point]]:
    """Every point the sinks would get from ``messages`` (in the order they arrived), per key."""
    sink = MemorySink()
    tracker = Tracker([sink], env_steps_before=env_steps_before, flush_s=math.inf)
    tracker.on_messages(messages)
    return sink.series


def tag(service: str, name: str) -> str:
    """The key of metric ``name`` of ``service``: its own name in the service's namespace (``train/policy_loss``),
    else under the service (every service reports ``proc/rss_mb``: ``gen/proc/rss_mb``, ``sim/proc/rss_mb``)."""
    return name if name.partition("/")[0] == service else f"{service}/{name}"


def _finite(value: Any) -> bool:
    return isinstance(value, (int, float)) and math.isfinite(value)


def steps_so_far(run_dir: str | Path) -> int:
    """The largest step in ``RUN_DIR/metrics.csv`` (0 when there is none): where a resumed run's env steps go
    on from."""
    path = Path(run_dir) / CSV_FILE
    try:
        with open(path, "rb") as fh:
            fh.seek(0, 2)
            size = fh.tell()
            fh.seek(max(0, size - 65536))
            tail = fh.read().decode(errors="replace").splitlines()
    except OSError:
        return 0
    best = 0
    for line in tail[1:] if len(tail) > 1 else tail:
        head = line.split(",", 1)[0]
        if head.isdigit():
            best = max(best, int(head))
    return best


def open_tracker(cfg: config_mod.Config, run_dir: str | Path) -> Tracker:
    """The tracker of the run in ``run_dir``, with every sink ``[log]`` asks for (``ebrl/services/log.py``)."""
    from ebrl import meta as meta_mod

    run_dir = Path(run_dir)
    meta = meta_mod.read(run_dir)
    info = RunInfo(cfg.run.name, run_dir, cfg, config_mod.dump_toml(cfg), meta)
    before = meta.get("resumed", [{}])[-1].get("env_steps_before", 0) if meta.get("resumed") else 0
    return Tracker(open_sinks(info, cfg.log), cfg.log.exclude, env_steps_before=before, flush_s=cfg.log.flush_s)
