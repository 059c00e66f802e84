"""Service base: one lifecycle for every EBRL process (bus, liveliness, stats, spans, control, shutdown).

A service subclass implements ``setup`` (declare subscriptions, build models),
``run`` (its main coroutine) and optionally ``teardown`` and ``metrics``. The
base owns everything else:

* SIGINT/SIGTERM set an ``asyncio.Event``; ``run`` is cancelled and given
  ``STOP_GRACE_S`` to finish, then the bus is flushed and closed;
* the liveliness token ``ebrl/live/<run>/<role>/<instance>`` is declared once
  ``setup`` has finished, so "live" means "ready";
* stats are published every ``run.stats_interval`` seconds; ``count(name, n)``
  counters become ``name`` (total) and ``name_per_s`` (rate over the interval);
* ``with self.span(label, lane):`` records a timeline span from any thread; spans are
  published in one ``SpanBatch`` per lane every ``SPAN_FLUSH_S``;
* control messages (stop, affinity, quota) are versioned and applied once.
"""

from __future__ import annotations

import argparse
import asyncio
import contextlib
import dataclasses
import logging
import os
import signal
import sys
import threading
import time
from typing import Any, Iterator

import psutil

from ebrl import config as config_mod, devices, procenv, sizes, threads
from ebrl import graph
from ebrl.bus import auth
from ebrl.bus.session import Bus, BusOptions
from ebrl.messages import Affinity, Event, Quota, SpanBatch, StatsReport, Stop, encode_message
from ebrl.meter import SPAN_BATCH_MAX, Meter

STOP_GRACE_S = 5.0
EXIT_GRACE_S = 3.0  # after a service stopped, its process exits within this (service_main)
SPAN_FLUSH_S = 0.2  # spans are published in one batch per lane this often (one message per span costs too much)
# The reason of a Stop that the launcher follows with a new process of the same service at once (a new GPU
# share): what the service holds that the next one can use is handed over, not dropped.
STOP_TO_RESTART = "new GPU share"


class Service:
    role = "service"

    def __init__(self, cfg: config_mod.Config, instance: int = 0, bus_options: BusOptions | None = None,
                 run_dir: str | None = None):
        self.cfg = cfg
        self.run_dir = run_dir or "."  # the run directory (where the launcher put the resolved config)
        self.run_name, self.instance = cfg.run.name, instance
        self.bus_options = bus_options or BusOptions(mode=cfg.bus.mode, connect=list(cfg.bus.connect),
                                                     config_file=cfg.bus.config_file,
                                                     max_message_bytes=cfg.bus.max_message_bytes,
                                                     secret_file=auth.secret_path(cfg.bus, self.run_dir),
                                                     role=self.role)
        self.log = logging.getLogger(f"ebrl.{self.role}")
        self.bus: Bus = None  # type: ignore[assignment]  # opened in main()
        self.stopping: asyncio.Event = None  # type: ignore[assignment]
        self.stop_reason = ""
        service, factor, after_s = config_mod.parse_slowdown(cfg.run.slowdown) if cfg.run.slowdown else ("", 1, 0)
        self.meter = Meter(
            spans=cfg.viz.spans, slowdown=(factor, after_s) if service == self.role and factor > 1 else None,
            on_slowdown=lambda f: self.event("slowdown", f"{self.role}/{self.instance}: injected slowdown x{f:g} "
                                                         "from now on"),
            on_full=self.flush_spans)
        self.reports = StatsReporter(self.run_name, self.role, instance, self.meter.started_at)
        self.keys = graph.keys_of(self.run_name, self.role, instance, service=True)  # every key it uses
        self.bounds: sizes.Bounds | None = None  # of the data keys it receives (message_bounds), before its bus opens
        self.device: Any = None  # the torch device of gen and train (``use_device``)
        self.memory_cap: float | None = None  # the fraction of the GPU's memory this process may allocate
        self.shares_process = False  # run with other services in one process (run.processes: ebrl.process)
        self.ready = threading.Event()  # set once setup() is done: a process of several starts the next then

    # --- to override ---------------------------------------------------------------

    async def setup(self) -> None:
        """Declare subscriptions, build models. The service is announced live after this."""

    async def run(self) -> None:
        """The service's work; return to stop the service."""
        await self.stopping.wait()

    async def teardown(self) -> None:
        """Release what setup acquired (called after run ended, before the bus closes)."""

    def metrics(self) -> dict[str, float]:
        """Service-specific metrics for the stats report (namespaced: sim/, gen/, train/)."""
        return {}

    async def message_bounds(self) -> sizes.Bounds | None:
        """The bounds of the data keys this service receives (:mod:`ebrl.sizes`), or None: none. Read before its bus
        opens (:func:`bounded`: Zenoh's receive limit is fixed then); kept in ``self.bounds``."""
        return None

    def on_affinity(self, cores: list[int]) -> None:
        """Apply a CPU affinity; the default pins this process."""
        os.sched_setaffinity(0, cores)

    def cores_in_use(self) -> list[int]:
        """The cores this service works on (reported as ``quota/cores``); the default: its affinity."""
        return sorted(os.sched_getaffinity(0))

    def on_quota(self, quota: Quota) -> None:
        """Apply a resource quota; the default sets torch's thread count (``ebrl.threads``) and, on a GPU, the
        memory cap."""
        if quota.threads:
            threads.set_threads(quota.threads, pool_only=True)  # the TorchPool thread's, before its next task
        if quota.mem_bytes and self.device is not None:
            self.memory_cap = devices.apply_memory_cap(self.device, quota.mem_bytes)

    def use_device(self, device: Any) -> None:
        """Run this service's torch work on ``device``: the launcher's GPU memory budget becomes its cap, and the
        device is said in the log, the run's events and every stats report (``<role>/cuda_*``)."""
        self.device = device
        self.memory_cap = devices.launch_memory_cap(device)
        where = devices.describe(device) + (f", memory cap {self.memory_cap:.0%}" if self.memory_cap else "")
        self.log.info("%s/%d on %s", self.role, self.instance, where)
        self.event("device", f"{self.role}/{self.instance} on {where}")

    # --- telemetry (ebrl.meter.Telemetry): for the service and the library code it drives -----

    def count(self, name: str, n: float = 1) -> None:
        """Add ``n`` to counter ``name`` (thread-safe); reported as total and per-second rate."""
        self.meter.count(name, n)

    @contextlib.contextmanager
    def span(self, label: str, lane: str | None = None) -> Iterator[None]:
        """Time a block and record it as a span of ``lane`` (published on ``ebrl/stats/<run>/spans/<lane>``)."""
        start = time.time()
        try:
            yield
        finally:
            self.publish_span(lane or self.role, label, start, time.time())

    def publish_span(self, lane: str, label: str, start: float, end: float, busy: bool = True) -> None:
        """Record a span for the next batch (see :meth:`Meter.publish_span`)."""
        self.meter.publish_span(lane, label, start, end, busy)

    def flush_spans(self) -> None:
        """Publish the spans recorded since the last flush, one ``SpanBatch`` per lane (any thread)."""
        for lane, rows in self.meter.take_spans().items():
            for at in range(0, len(rows), SPAN_BATCH_MAX):  # other threads may have added past the bound
                starts, ends, labels = zip(*rows[at:at + SPAN_BATCH_MAX])
                self.bus.put_nowait(self.keys.put("spans", lane=lane), SpanBatch(
                    lane=lane, service=self.role, instance=self.instance, start=list(starts), end=list(ends),
                    label=list(labels)))

    def event(self, kind: str, text: str) -> None:
        """Add a line to the run's event log (``ebrl/stats/<run>/events/<role>``), from any thread."""
        self.bus.put_nowait(self.keys.put("events"),
                            Event(time=time.time(), service=self.role, instance=self.instance, kind=kind, text=text))

    # --- lifecycle ------------------------------------------------------------------

    async def main(self, bus: Any = None, signals: bool = True) -> int:
        """Run the service to its end; its exit status. ``bus``: any object with the ``Bus`` API (e.g. an
        ``ebrl.bus.memory.MemoryBus``, to run several services in one process); default: a Zenoh ``Bus``
        from ``bus_options``. ``signals=False`` leaves SIGINT/SIGTERM to the caller."""
        loop = asyncio.get_running_loop()
        self.stopping = asyncio.Event()
        if signals:
            for sig in (signal.SIGINT, signal.SIGTERM):
                loop.add_signal_handler(sig, self.request_stop, f"signal {sig.name}")
        self.bounds = self.bounds or await self.message_bounds()
        self.bus = bus if bus is not None else Bus(bounded(self.bus_options, self.bounds))
        exit_code = 0
        try:
            await self.setup()
            self.ready.set()
            self.controls = ControlInbox(self)
            self.bus.declare_token(self.keys.token())
            self.log.info("%s/%d ready", self.role, self.instance)
            stats_task = asyncio.create_task(self._stats_loop())
            spans_task = asyncio.create_task(self._spans_loop())
            run_task = asyncio.create_task(self.run())
            stop_task = asyncio.create_task(self.stopping.wait())
            done, _ = await asyncio.wait({run_task, stop_task}, return_when=asyncio.FIRST_COMPLETED)
            if run_task in done:
                exc = run_task.exception()
                if exc is not None:
                    self.log.error("run failed", exc_info=exc)
                    exit_code = 1
            else:
                run_task.cancel()
                with contextlib.suppress(asyncio.CancelledError, asyncio.TimeoutError, Exception):
                    await asyncio.wait_for(run_task, STOP_GRACE_S)
            stop_task.cancel()
            stats_task.cancel()
            spans_task.cancel()
            await self.teardown()
            self.flush_spans()
            await self.publish_stats()
        finally:
            await self.bus.close()
        self.log.info("%s/%d stopped", self.role, self.instance)
        return exit_code

    def request_stop(self, reason: str) -> None:
        if not self.stopping.is_set():
            self.log.info("stopping: %s", reason)
            self.stop_reason = reason
            self.stopping.set()

    async def _spans_loop(self) -> None:
        while True:
            asleep = time.monotonic()
            await asyncio.sleep(SPAN_FLUSH_S)
            # how late the event loop woke: the longest it was held since the last report (proc/loop_lag_max_ms)
            self.reports.loop_lag(time.monotonic() - asleep - SPAN_FLUSH_S)
            self.flush_spans()

    async def _stats_loop(self) -> None:
        self.meter.start_interval()
        self.reports.start()
        while True:
            await asyncio.sleep(self.cfg.run.stats_interval)
            await self.publish_stats()

    async def publish_report(self, metrics: dict[str, float]) -> None:
        """Publish a stats report of just ``metrics`` now, on this service's stats key and numbered with the
        periodic ones: for a result that happens once (an evaluation), not every interval."""
        await self.bus.put(self.keys.put("stats"), self.reports.next(dict(metrics)))

    async def publish_stats(self) -> None:
        """The periodic report, published every interval; or now, for a result the run waits on (the update that
        reaches ``run.iterations`` or a target), so that the launcher acts on it at once."""
        try:
            report = self._report()
        except Exception as exc:
            self.log.warning("stats not reported: %s", exc)
            return
        await self.bus.put(self.keys.put("stats"), report)

    def _report(self) -> StatsReport:
        """The periodic report: the meter's counters and rates, what every process reports, the service's own."""
        metrics = self.meter.metrics()
        metrics.update(self.reports.process_metrics(self.bus))
        metrics["quota/cores"] = float(len(self.cores_in_use()))
        if self.device is not None:
            metrics.update(devices.metrics(self.role, self.device, self.memory_cap))
        metrics.update(self.metrics())
        return self.reports.next(metrics)


async def env_info(service: Service) -> Any:
    """The run's :class:`~ebrl.envs.EnvInfo` for ``service`` (the env built once off the event loop, then closed),
    read once: its bounds (``message_bounds``, before its bus opens) and its setup both need it."""
    if getattr(service, "_env_info", None) is None:
        from ebrl.envs import EnvSpec, describe

        service._env_info = await asyncio.get_running_loop().run_in_executor(
            None, describe, EnvSpec.from_config(service.cfg.env))
    return service._env_info


def bounded(options: BusOptions, bounds: sizes.Bounds | None) -> BusOptions:
    """``options`` with Zenoh's receive limit lowered to the largest message of ``bounds`` (:mod:`ebrl.sizes`):
    Zenoh then drops a larger message before it is whole, so it never costs more memory than that."""
    if bounds is None:
        return options
    return dataclasses.replace(options, max_message_bytes=min(options.max_message_bytes, bounds.link))


def bus_metrics(bus: Any) -> dict[str, float]:
    """What a process's bus dropped (``bus/*``), for its stats report: malformed payloads (oversized ones among
    them, also counted apart) and messages its full sender queue dropped; in a process of several services, the
    messages handed over in it and those its role may not send. Services and the launcher report it."""
    metrics = {"bus/malformed": float(sum(bus.malformed.values())),
               "bus/oversized": float(sum(bus.oversized.values())),
               "bus/sender_dropped": float(bus.sender_dropped)}
    if hasattr(bus, "local"):  # a service sharing its process (ebrl.bus.local)
        metrics["bus/local"] = float(bus.local)
        metrics["bus/refused"] = float(sum(bus.refused.values()))
    return metrics


class StatsReporter:
    """A service's stats reports: numbered in order (``seq``), with what every process reports about itself
    (``bus/*`` drops, ``proc/*`` CPU, memory, uptime and event-loop lateness, ``quota/threads``)."""

    def __init__(self, run: str, role: str, instance: int, started_at: float):
        self.run, self.role, self.instance, self.started_at = run, role, instance, started_at
        self.seq = 0
        self._proc = psutil.Process()
        self._loop_lag = 0.0  # seconds: the event loop's longest lateness since the last report

    def start(self) -> None:
        """Start the first interval of ``proc/cpu_percent``."""
        self._proc.cpu_percent()

    def loop_lag(self, seconds: float) -> None:
        """The event loop woke ``seconds`` late; the longest since the last report is reported."""
        self._loop_lag = max(self._loop_lag, seconds)

    def process_metrics(self, bus: Any) -> dict[str, float]:
        metrics = {**bus_metrics(bus),
                   "proc/cpu_percent": self._proc.cpu_percent(),
                   "proc/rss_mb": self._proc.memory_info().rss / 2**20,
                   "proc/uptime_s": time.time() - self.started_at,
                   "proc/loop_lag_max_ms": 1000 * self._loop_lag}
        self._loop_lag = 0.0
        if "torch" in sys.modules:
            metrics["quota/threads"] = float(threads.wanted() or sys.modules["torch"].get_num_threads())
        return metrics

    def next(self, metrics: dict[str, float]) -> StatsReport:
        """``metrics`` as the next report."""
        report = StatsReport(run=self.run, service=self.role, instance=self.instance, time=time.time(),
                             seq=self.seq, metrics=metrics)
        self.seq += 1
        return report


CONTROL_STEP = 1000
"""How far past the last applied version (0 before any) a control version may be: the allocator numbers its
plans 1, 2, 3 ... (``ebrl.alloc.placement``), one per re-plan or revert, and each needs ``alloc.window`` +
``alloc.patience`` stats reports (40 at the defaults: 40 s at run.stats_interval = 1) after the one before, so a
real step of 1000 is over 11 hours of nothing but re-planning, and a service restarted that late still follows. A
forged version of 2**53 would pin a service for good (every real plan after it "already applied"); one within the
step can at worst hold it for the 1000 plans after it."""


def control_version_refused(version: int, last: int) -> str | None:
    """Why a control version (Quota, Affinity, GpuShare) is refused after ``last`` (the last applied, 0 before
    any), or None: it may be at most :data:`CONTROL_STEP` past it."""
    if version > last + CONTROL_STEP:
        return f"version {version} is more than {CONTROL_STEP} past the last applied, {last}"
    return None


class ControlInbox:
    """A service's control keys (``ebrl/ctl/<run>/<role>/<instance>/<kind>``): ``stop``; ``affinity`` and
    ``quota``, applied once per version (a repeated or older version is counted and ignored, one more than
    :data:`CONTROL_STEP` past the last applied counted as ``ctl/version_refused`` and dropped); ``status``, a
    query answered with the service's stats report."""

    def __init__(self, service: Service):
        self.service = service
        self.versions: dict[str, int] = {}
        self.refused = 0  # versions too far past the last applied (control_version_refused)
        self._tasks: set[asyncio.Task] = set()
        s = service
        self._consume("stop", Stop, lambda m: s.request_stop(m.reason))
        self._consume("affinity", Affinity, lambda m: self._versioned("affinity", m, lambda: s.on_affinity(m.cores)))
        self._consume("quota", Quota, lambda m: self._versioned("quota", m, lambda: s.on_quota(m)))

        async def status(_: bytes) -> bytes:
            return encode_message(s._report())

        s.bus.declare_queryable(s.keys.answer("status"), status)

    def _consume(self, kind: str, cls: type, apply: Any) -> None:
        key = self.service.keys.sub("ctl", kind=kind)
        sub = self.service.bus.subscribe(key, cls, policy="latest", capacity=8)

        async def consume() -> None:
            async for _, msg in sub:
                try:
                    apply(msg)
                except Exception as exc:
                    self.service.log.warning("control %s not applied: %s", key, exc)

        self._tasks.add(asyncio.create_task(consume()))  # keep a reference: the loop holds tasks weakly

    def _versioned(self, kind: str, msg: Any, apply: Any) -> None:
        s = self.service
        last = self.versions.get(kind, 0)
        if msg.version <= self.versions.get(kind, -1):
            s.count(f"ctl/{kind}_ignored")
            return
        if refused := control_version_refused(msg.version, last):
            s.count("ctl/version_refused")
            if not self.refused:
                s.log.warning("control %s refused: %s (further ones only counted)", kind, refused)
            self.refused += 1
            return
        apply()
        self.versions[kind] = msg.version
        s.count(f"ctl/{kind}_applied")
        s.log.info("applied %s version %d", kind, msg.version)
        s.event(kind, f"{s.role}/{s.instance} applied {kind} v{msg.version}: {_describe_control(msg)}")


def _describe_control(msg: Any) -> str:
    if isinstance(msg, Affinity):
        return f"cores {msg.cores}"
    fields = {k: v for k, v in vars(msg).items() if k != "version" and v is not None}
    return " ".join(f"{k}={v}" for k, v in fields.items()) or "-"


def service_main(cls: type[Service], argv: list[str] | None = None) -> None:
    """Entry point of ``python -m ebrl.services.<role>``: parse args, configure logging, run."""
    parser = argparse.ArgumentParser(prog=f"ebrl.services.{cls.role}")
    parser.add_argument("--config", required=True, help="resolved TOML config")
    parser.add_argument("--instance", type=int, default=0)
    parser.add_argument("--connect", action="append", default=[], help="bus endpoint to connect to")
    parser.add_argument("--set", action="append", default=[], dest="overrides", metavar="SECTION.KEY=VALUE")
    args = parser.parse_args(argv)
    try:
        cfg = config_mod.load(args.config, args.overrides)
    except config_mod.ConfigError as exc:
        print(f"config error: {exc}", file=sys.stderr)
        sys.exit(2)
    logging.basicConfig(level=cfg.run.log_level.upper(),
                        format=f"%(asctime)s {cls.role}/{args.instance} %(levelname)s %(name)s: %(message)s")
    # Started by a launcher: join through it alone. Between hosts the launchers route; a service that also
    # linked to another host's launcher would make a loop that Zenoh does not propagate declarations over.
    run_dir = os.path.dirname(os.path.abspath(args.config))
    options = BusOptions(mode=cfg.bus.mode, connect=args.connect or list(cfg.bus.connect),
                         listen=["tcp/127.0.0.1:0"], config_file=cfg.bus.config_file,
                         max_message_bytes=cfg.bus.max_message_bytes, secret_file=auth.secret_path(cfg.bus, run_dir),
                         role=cls.role, identity=procenv.take_identity())  # its instance's, from its launcher
    service = cls(cfg, args.instance, options, run_dir=run_dir)

    async def run_then_arm() -> int:
        code = await service.main()
        exit_within(EXIT_GRACE_S, code, f"{cls.role}/{args.instance}")
        return code

    sys.exit(asyncio.run(run_then_arm()))


def exit_within(seconds: float, code: int, name: str) -> None:
    """Once a service has stopped (its state saved, its bus closed), its process exits within ``seconds``
    even if a thread would hold interpreter exit; which threads did is written to its log."""

    def force() -> None:
        held = [t.name for t in threading.enumerate()
                if t.is_alive() and not t.daemon and t is not threading.main_thread()]
        print(f"{name}: exit held for {seconds:.0f} s after stopping (threads: {', '.join(held) or '-'}); exiting",
              file=sys.stderr, flush=True)
        logging.shutdown()
        os._exit(code)

    timer = threading.Timer(seconds, force)
    timer.daemon = True
    timer.start()
