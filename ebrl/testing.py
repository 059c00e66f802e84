"""A real ``ebrl up`` and its stats stream, for tests, ``ebrl bench`` and benchmarks/; and any services of a run in
one process, on the in-memory bus.

:class:`Run` starts ``ebrl up CONFIG --set ...`` as a user would (a subprocess with its own bus on a
free loopback port) and stops it with SIGINT, then SIGKILL; :class:`InProcessRun` runs the services of one
run (any of sim, gen, train, eval, log, alloc, viz) as tasks of the caller's event loop over
:mod:`ebrl.bus.memory`, so that a few iterations take seconds and every message can be watched;
:class:`StatsWatcher` keeps every :class:`~ebrl.messages.StatsReport` of either kind of run;
:class:`Output` keeps what a subprocess prints (a run's launcher, ``ebrl router``). Waiting is always
for a condition with a deadline, never for a fixed time, and a wait that fails says what it waited for
and how the run ended.
"""

from __future__ import annotations

import asyncio
import json
import os
import re
import signal
import subprocess
import sys
import threading
import time
from pathlib import Path
from typing import Any, Callable, Sequence

import zenoh

from ebrl import config as config_mod
from ebrl import graph
from ebrl.bus import auth
from ebrl.bus.session import BusOptions, zenoh_config
from ebrl.bus.endpoints import free_port
from ebrl.bus.memory import MemoryBus, MemoryNetwork
from ebrl.messages import MessageError, StatsReport, decode_stats_sample
from ebrl.process import service_class

__all__ = ["InProcessRun", "Output", "Run", "RunError", "StatsWatcher", "free_port", "run_name", "service_class",
           "source", "up_command", "up_sets"]

REPO = Path(__file__).resolve().parent.parent  # where `ebrl` is (a clone's root, or site-packages)
STOP_S = 30.0  # after SIGINT, before SIGKILL (the launcher itself stops every service within SHUTDOWN_S)
STARTUP_S = 300.0  # default deadline for the launcher's first line (generous: shared, loaded machines)
TAIL_LINES = 40


class RunError(RuntimeError):
    """A run ended, or a wait for it ran out of time; the message ends with the run's last output lines."""


def up_sets(out_dir: str | os.PathLike, port: int, name: str | None = None, stats_interval: float | None = 0.5,
            overrides: Sequence[str] = ()) -> list[str]:
    """The ``--set`` items of a harnessed run: its name, output directory, loopback bus and stats interval,
    then ``overrides`` (last, so that they win: a ``run.name`` there is the name the run gets)."""
    sets = [f"run.name={name}"] if name is not None else []
    sets += [f"run.output_dir={json.dumps(str(out_dir))}", f'bus.listen=["tcp/127.0.0.1:{port}"]']
    if stats_interval is not None:
        sets.append(f"run.stats_interval={stats_interval}")
    return [*sets, *overrides]


def up_command(config: str | os.PathLike, sets: Sequence[str], args: Sequence[str] = ()) -> list[str]:
    """``python -m ebrl.cli up CONFIG ARGS --set ...`` with this interpreter."""
    cmd = [sys.executable, "-m", "ebrl.cli", "up", str(config), *args]
    for item in sets:
        cmd += ["--set", item]
    return cmd


def run_name(config: str | os.PathLike, sets: Sequence[str], cwd: str | os.PathLike | None = None) -> str:
    """The name ``ebrl up CONFIG --set SETS`` gives its run: the config's, after every override in order
    (the last ``run.name=`` wins, as in ``ebrl up``). Raises ConfigError for a config ``ebrl up`` refuses."""
    path = Path(config) if cwd is None else Path(cwd) / config
    return config_mod.load(str(path), list(sets)).run.name


def source(report: StatsReport) -> str:
    """``<service>/<instance>`` of a report, e.g. ``sim/0``: how stats are looked up here."""
    return f"{report.service}/{report.instance}"


class Output:
    """What a subprocess prints (its stdout, with stderr merged into it), read line by line by a thread so
    that the pipe never fills; also written to ``log`` if given. ``label`` names the process in errors."""

    def __init__(self, proc: subprocess.Popen, label: str, log: str | os.PathLike | None = None):
        self.proc, self.label = proc, label
        self._lines: list[str] = []
        self._changed = threading.Condition()
        self._reader = threading.Thread(target=self._read, args=(log,), name=f"output of {label}", daemon=True)
        self._reader.start()

    def _read(self, log: str | os.PathLike | None) -> None:
        fh = open(log, "w") if log is not None else None
        try:
            for line in self.proc.stdout:
                if fh is not None:
                    fh.write(line)
                    fh.flush()
                with self._changed:
                    self._lines.append(line)
                    self._changed.notify_all()
        finally:
            if fh is not None:
                fh.close()
            with self._changed:
                self._changed.notify_all()

    @property
    def text(self) -> str:
        """Everything printed so far."""
        with self._changed:
            return "".join(self._lines)

    def tail(self, lines: int = TAIL_LINES) -> str:
        with self._changed:
            return "".join(self._lines[-lines:])

    def join(self, timeout: float = 10.0) -> None:
        """Wait for the rest of the output once the process has ended."""
        self._reader.join(timeout)

    def error(self, what: str) -> RunError:
        """A RunError saying ``what``, naming the process and ending with its last output lines."""
        state = "still running" if self.proc.poll() is None else f"exit status {self.proc.returncode}"
        return RunError(f"{self.label} ({state}): {what}. Its last lines:\n{self.tail()}")

    def wait_for_line(self, match: str | Callable[[str], bool], timeout: float = STARTUP_S, what: str = "") -> str:
        """The first line printed so far or later that contains ``match`` (or satisfies it); raises RunError
        naming ``what`` (default: the line looked for) when the output ends without one or ``timeout`` s pass."""
        test = match if callable(match) else (lambda line: match in line)
        what = what or (f"a line with {match!r}" if isinstance(match, str) else "the line looked for")
        deadline = time.monotonic() + timeout
        seen = 0
        with self._changed:
            while True:
                for line in self._lines[seen:]:
                    if test(line):
                        return line
                seen = len(self._lines)
                if not self._reader.is_alive():
                    raise self.error(f"its output ended without {what}")
                left = deadline - time.monotonic()
                if left <= 0:
                    raise self.error(f"gave up waiting for {what} after {timeout:g} s")
                self._changed.wait(min(left, 1.0))


class Run:
    """``ebrl up CONFIG --set ...`` running as a subprocess on a free loopback port.

    ``name`` is the name asked for; :attr:`name` is the one the run got (a ``run.name`` among
    ``overrides`` wins). What the launcher prints is kept (:attr:`output`, :meth:`wait_for_line`), also in
    ``log`` if given. ``package``: the directory whose ``ebrl`` the run imports (default: this one's, the checkout
    or the installed package), e.g. a copy with a change to try. Leaving the ``with`` block stops the run
    (:meth:`stop`)."""

    _RUN_LINE = "run {name}: "  # the launcher's first line: "run NAME: RUN_DIR  (bus ENDPOINT)"

    def __init__(self, config: str | os.PathLike, *overrides: str, name: str, out_dir: str | os.PathLike,
                 args: Sequence[str] = (), port: int | None = None, stats_interval: float | None = 0.5,
                 log: str | os.PathLike | None = None, cwd: str | os.PathLike | None = None,
                 package: str | os.PathLike | None = None):
        self.port = port or free_port()
        self.endpoint = f"tcp/127.0.0.1:{self.port}"
        sets = up_sets(out_dir, self.port, name, stats_interval, overrides)
        self.name = run_name(config, sets, cwd)
        self.command = up_command(config, sets, args)
        env = dict(os.environ)
        first = str(REPO if package is None else package)
        env["PYTHONPATH"] = os.pathsep.join(p for p in (first, env.get("PYTHONPATH", "")) if p)
        self._run_dir: Path | None = None
        self.proc = subprocess.Popen(self.command, cwd=cwd, env=env, stdin=subprocess.DEVNULL,
                                     stdout=subprocess.PIPE, stderr=subprocess.STDOUT, text=True)
        self._output = Output(self.proc, f"ebrl up (run {self.name})", log)

    def __enter__(self) -> "Run":
        return self

    def __exit__(self, *exc) -> None:
        self.stop()

    def __repr__(self) -> str:
        state = "running" if self.proc.poll() is None else f"exit {self.proc.returncode}"
        return f"<ebrl up run {self.name} on {self.endpoint}, {state}>"

    # --- output -------------------------------------------------------------------------------------

    @property
    def output(self) -> str:
        """Everything the launcher printed so far."""
        return self._output.text

    def tail(self, lines: int = TAIL_LINES) -> str:
        return self._output.tail(lines)

    def wait_for_line(self, match: str | Callable[[str], bool], timeout: float = STARTUP_S, what: str = "") -> str:
        """The first line the launcher printed (so far or later) that contains ``match`` or satisfies it."""
        return self._output.wait_for_line(match, timeout, what)

    def error(self, what: str) -> RunError:
        """A RunError saying ``what``, naming this run and ending with its last output lines."""
        return self._output.error(what)

    @property
    def run_dir(self) -> Path:
        """The run directory, as the launcher announced it (waits for that line, at most STARTUP_S)."""
        if self._run_dir is None:
            head = self._RUN_LINE.format(name=self.name)
            line = self.wait_for_line(lambda text: text.startswith(head), what=f"its first line, {head}RUN_DIR")
            found = re.match(re.escape(head) + r"(.+?)  \(", line)
            if found is None:
                raise self.error(f"cannot read the run directory from {line.strip()!r}")
            self._run_dir = Path(found.group(1))
        return self._run_dir

    # --- lifetime -----------------------------------------------------------------------------------

    def poll(self) -> int | None:
        return self.proc.poll()

    @property
    def returncode(self) -> int | None:
        return self.proc.returncode

    def check_running(self, what: str) -> None:
        """Raise RunError if the run has ended (``what``: what the caller was waiting for)."""
        if self.proc.poll() is not None:
            raise self.error(f"the run ended while waiting for {what}")

    def wait(self, timeout: float) -> int:
        """Wait for the run to end by itself; its exit status. Raises RunError after ``timeout`` seconds (the
        run is left running: leaving the ``with`` block stops it)."""
        try:
            code = self.proc.wait(timeout)
        except subprocess.TimeoutExpired:
            raise self.error(f"it did not end within {timeout:.0f} s") from None
        self._output.join()  # the rest of its output
        return code

    def interrupt(self) -> None:
        """Ctrl-C: SIGINT to the launcher, which stops every service."""
        if self.proc.poll() is None:
            self.proc.send_signal(signal.SIGINT)

    def stop(self, timeout: float = STOP_S) -> int:
        """SIGINT, then SIGKILL after ``timeout`` seconds; the exit status (130: stopped by SIGINT)."""
        self.interrupt()
        try:
            self.proc.wait(timeout)
        except subprocess.TimeoutExpired:
            self.proc.kill()
            self.proc.wait()
        self._output.join()
        return self.proc.returncode


class InProcessRun:
    """Services of one run as tasks of the running event loop, on one in-memory bus network: the real services
    (``ebrl/services/<role>.py``), models, env worker processes and protocols; only the transport is in memory.

    ``roles``: ``"sim"`` or ``("sim", 1)`` (an instance other than 0). ``make_bus(network, role)`` gives each
    service its bus (default: a :class:`~ebrl.bus.memory.MemoryBus`; a test may record what it sends).
    :attr:`stats` watches every stats report, :attr:`watch` is a bus of the same network for anything else::

        async with InProcessRun(cfg, ("train", "gen", "sim"), tmp_path) as run:
            await run.stats.until(lambda: run.stats.latest("train/0", "train/policy_version", 0) >= 2, 120, "v2")

    Leaving stops every service (as ``ctl/.../stop`` would) and raises :class:`RunError` unless each exited 0.
    The services' CPU affinity controls pin this process's threads; leaving gives the caller's back."""

    def __init__(self, cfg: config_mod.Config, roles: Sequence[str | tuple[str, int]], run_dir: str | os.PathLike,
                 make_bus: Callable[[MemoryNetwork, str], Any] | None = None):
        self.cfg, self.name, self.run_dir = cfg, cfg.run.name, Path(run_dir)
        self.roles = [(r, 0) if isinstance(r, str) else r for r in roles]
        self.make_bus = make_bus or (lambda network, role: MemoryBus(network))
        self.services: list[Any] = []
        self.tasks: list[asyncio.Task] = []
        self.codes: list[Any] = []

    async def __aenter__(self) -> "InProcessRun":
        self._affinity = os.sched_getaffinity(0)
        self.network = MemoryNetwork()
        self.watch = MemoryBus(self.network)
        self.stats = StatsWatcher(self)
        for role, instance in self.roles:
            service = service_class(role)(self.cfg, instance, run_dir=str(self.run_dir))
            self.services.append(service)
            self.tasks.append(asyncio.create_task(service.main(bus=self.make_bus(self.network, role), signals=False)))
        return self

    async def __aexit__(self, kind, exc, tb) -> None:
        codes = await self.stop()
        if kind is None and any(code != 0 for code in codes):
            raise self.error("services did not exit 0")

    async def stop(self, timeout: float = 60.0) -> list[Any]:
        """Stop every service; their exit codes (an exception where one raised), in ``roles`` order."""
        for service in self.services:
            if service.stopping is not None:
                service.request_stop("test over")
        try:
            self.codes = await asyncio.wait_for(asyncio.gather(*self.tasks, return_exceptions=True), timeout)
        finally:
            self.stats.close()
            await self.watch.close()
            os.sched_setaffinity(0, self._affinity)
        return self.codes

    def service(self, role: str, instance: int = 0) -> Any:
        return next(s for s in self.services if s.role == role and s.instance == instance)

    def ended(self) -> list[str]:
        """``role/instance (code)`` of each service that has ended."""
        return [f"{s.role}/{s.instance} ({t.exception() or t.result() if not t.cancelled() else 'cancelled'})"
                for s, t in zip(self.services, self.tasks) if t.done()]

    def check_running(self, what: str) -> None:
        if ended := self.ended():
            raise self.error(f"{', '.join(ended)} ended while waiting for {what}")

    def error(self, what: str) -> RunError:
        codes = ", ".join(f"{role}/{instance}: {code!r}" for (role, instance), code in zip(self.roles, self.codes))
        return RunError(f"in-process run {self.name}: {what}" + (f" (exit codes {codes})" if codes else ""))


def run_session_config(run: Run, endpoint: str | None = None, role: str = "observer") -> zenoh.Config:
    """A Zenoh config that joins ``run``'s bus, a client of its launcher: signed in with the run's secret when
    it has one, as ``role`` (``observer`` watches stats; ``launcher`` may send anything, as another host's
    launcher; a service's role line signs in only to a mesh, ``bus.mode = "peer"``: a client-mode launcher
    admits the services' instance identities alone, ``ebrl.bus.auth``), else open."""
    secret = auth.secret_path(config_mod.load(run.run_dir / "config.toml").bus, run.run_dir)
    return zenoh_config(BusOptions(mode="client", connect=[endpoint or run.endpoint], listen=[], secret_file=secret,
                                   role=role))


class StatsWatcher:
    """Every StatsReport of one run, as its bus delivers them, for either kind of run: of a :class:`Run`, a Zenoh
    subscriber of ``ebrl/stats/<run>/**`` (``role``'s stats flow) connected to the run's endpoint (``session`` is that Zenoh
    session, for a test that also publishes on the run's bus); of an :class:`InProcessRun`, a subscriber on its
    in-memory network. Thread-safe: filled by the transport's callback."""

    def __init__(self, run: Run | InProcessRun, endpoint: str | None = None,
                 role: str = "observer"):
        self.run = run
        stats = graph.keys_of(run.name, role).sub("stats")
        self._lock = threading.Lock()
        self._reports: list[StatsReport] = []
        self.malformed = 0
        self.session: zenoh.Session | None = None
        if isinstance(run, InProcessRun):
            self._subscriber = run.watch.subscribe_raw(stats, self._on_payload)
        else:
            self.session = zenoh.open(run_session_config(run, endpoint, role))
            self._subscriber = self.session.declare_subscriber(
                stats, lambda sample: self._on_payload(str(sample.key_expr),
                                                                          sample.payload.to_bytes()))

    def __enter__(self) -> "StatsWatcher":
        return self

    def __exit__(self, *exc) -> None:
        self.close()

    def close(self) -> None:
        """Stop listening; what was received stays readable."""
        if self._subscriber is not None:
            self._subscriber.undeclare()
            self._subscriber = None
            if self.session is not None:
                self.session.close()

    def _on_payload(self, key: str, payload: bytes) -> None:
        try:
            message = decode_stats_sample(key, payload)
        except MessageError:
            with self._lock:
                self.malformed += 1
            return
        if isinstance(message, StatsReport):  # spans and events are not stats
            with self._lock:
                self._reports.append(message)

    # --- reading ------------------------------------------------------------------------------------

    def reports(self, of: str | None = None) -> list[StatsReport]:
        """Reports received so far in arrival order: every source's, or those of ``of`` (e.g. ``sim/0``)."""
        with self._lock:
            return [r for r in self._reports if of is None or source(r) == of]

    def latest_report(self, of: str, metric: str) -> StatsReport | None:
        """The newest report of ``of`` that has ``metric``."""
        with self._lock:
            return next((r for r in reversed(self._reports) if source(r) == of and metric in r.metrics), None)

    def latest(self, of: str, metric: str, default: float | None = None) -> float | None:
        """The newest value of ``metric`` reported by ``of`` (``default`` if none yet)."""
        report = self.latest_report(of, metric)
        return default if report is None else report.metrics[metric]

    def values(self, of: str, metric: str) -> list[float]:
        """Every value of ``metric`` reported by ``of``, in arrival order."""
        return [r.metrics[metric] for r in self.reports(of) if metric in r.metrics]

    def by_source(self) -> dict[str, list[dict[str, float]]]:
        """``{"<service>/<instance>": [metrics, ...]}`` in arrival order."""
        out: dict[str, list[dict[str, float]]] = {}
        for report in self.reports():
            out.setdefault(source(report), []).append(report.metrics)
        return out

    def between(self, t0: float, t1: float) -> dict[str, list[StatsReport]]:
        """Per source, the reports stamped from ``t0`` to ``t1`` (epoch seconds, both included)."""
        out: dict[str, list[StatsReport]] = {}
        for report in self.reports():
            if t0 <= report.time <= t1:
                out.setdefault(source(report), []).append(report)
        return out

    # --- waiting ------------------------------------------------------------------------------------

    def wait_for(self, predicate: Callable[[], object], timeout: float, what: str) -> None:
        """Poll ``predicate()`` until it is true; raise RunError naming ``what`` (and ending with the run's
        output) if the run ends first or ``timeout`` seconds pass."""
        deadline = time.monotonic() + timeout
        while not predicate():
            self.run.check_running(what)
            if time.monotonic() > deadline:
                raise self.run.error(f"gave up waiting for {what} after {timeout:g} s")
            time.sleep(0.2)

    async def until(self, predicate: Callable[[], object], timeout: float, what: str) -> None:
        """:meth:`wait_for` without blocking the event loop (an :class:`InProcessRun` runs on it)."""
        deadline = time.monotonic() + timeout
        while not predicate():
            self.run.check_running(what)
            if time.monotonic() > deadline:
                raise self.run.error(f"gave up waiting for {what} after {timeout:g} s")
            await asyncio.sleep(0.05)
