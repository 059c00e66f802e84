"""One trial: a real ``ebrl up`` of the sweep's config with the trial's params, followed over the bus
(``ebrl.watch``) with its curve handed to Optuna as it arrives, and stopped as Ctrl-C stops a run when it is
pruned, over its budget or the sweep is interrupted.

The launcher runs in a process group of its own, so that Ctrl-C on ``ebrl sweep`` reaches the sweep alone,
which then stops each trial in order: SIGINT to the launcher's group (the launcher stops its services, which
are in groups of their own, and writes its summary), SIGTERM after :data:`STOP_S`, SIGKILL after
:data:`TERM_S` more; whatever is left in the launcher's group is killed before it is reaped. A launcher whose
sweep dies (even by SIGKILL) gets SIGTERM (``PR_SET_PDEATHSIG``, set by :data:`SHIM` before ``ebrl up`` starts),
so no trial outlives its sweep.
"""

from __future__ import annotations

import contextlib
import dataclasses
import json
import os
import re
import signal
import subprocess
import sys
import threading
import time
from pathlib import Path
from typing import Any, Iterator

from ebrl import stats
from ebrl.messages import StatsReport
from ebrl.sweep.curve import Curve, report_and_check
from ebrl.sweep.spec import Budget, Objective

STOP_S = 60.0  # after SIGINT: a launcher stops every service within ~10 s, a loaded host's within a minute
TERM_S = 20.0  # after SIGTERM, before SIGKILL
START_S = 600.0  # for the launcher's first line (its run directory): imports and preflight on a loaded host
IDLE_S = 2.0  # the stream is reopened after this long without a report while the run lives
TAIL = 6  # log lines in a failed trial's reason

# Runs in the trial's launcher process before ``ebrl up``: dies with the sweep, pinned to its slot's cores.
SHIM = """import ctypes, os, signal, sys
ctypes.CDLL(None, use_errno=True).prctl(1, signal.SIGTERM)  # PR_SET_PDEATHSIG
if os.getppid() != int(sys.argv[1]):
    sys.exit(143)
if sys.argv[2]:
    os.sched_setaffinity(0, [int(c) for c in sys.argv[2].split(",")])
os.execv(sys.executable, [sys.executable, "-m", "ebrl.cli", *sys.argv[3:]])
"""


@dataclasses.dataclass
class Outcome:
    """How a trial ended: ``complete`` (its value), ``pruned``, ``failed`` (``reason``) or ``interrupted``
    (the sweep was stopped: queued again)."""

    state: str
    value: float | None = None
    reason: str = ""
    run_dir: Path | None = None
    step: int = 0
    exit_code: int | None = None


class TrialRun:
    """``ebrl up CONFIG --set ...`` of one trial, its output in ``trials_dir/NAME.log``; ``cores``: the cores its
    launcher (and so every service) is pinned to, None for all."""

    def __init__(self, config: str, overrides: list[str], name: str, trials_dir: Path,
                 cores: list[int] | None = None):
        self.name, self.log_path = name, trials_dir / f"{name}.log"
        self.argv = [sys.executable, "-c", SHIM, str(os.getpid()), ",".join(map(str, cores or ())), "up", config]
        for item in overrides:
            self.argv += ["--set", item]
        self.run_dir: Path | None = None
        self.proc: subprocess.Popen | None = None
        self.started = 0.0

    def start(self) -> None:
        self.log_path.parent.mkdir(parents=True, exist_ok=True)
        env = dict(os.environ)
        here = str(Path(__file__).resolve().parent.parent.parent)  # where ebrl is: a clone runs without installing
        env["PYTHONPATH"] = os.pathsep.join(p for p in (here, env.get("PYTHONPATH", "")) if p)
        with open(self.log_path, "w") as log:
            self.proc = subprocess.Popen(self.argv, stdin=subprocess.DEVNULL, stdout=log, stderr=subprocess.STDOUT,
                                         env=env, process_group=0)
        self.started = time.monotonic()

    def exited(self, timeout: float = 0.0) -> bool:
        """Whether the launcher has exited (within ``timeout`` s), leaving it unreaped: its group id stays its own
        until :meth:`halt` has killed what is left in the group."""
        deadline = time.monotonic() + timeout
        while True:
            if self.proc.returncode is not None or os.waitid(os.P_PID, self.proc.pid,
                                                             os.WEXITED | os.WNOHANG | os.WNOWAIT) is not None:
                return True
            if time.monotonic() >= deadline:
                return False
            time.sleep(min(0.2, max(0.0, deadline - time.monotonic())))

    def wait_run_dir(self, stopping: threading.Event) -> Path | None:
        """The run's directory, from the launcher's first line; None where it exited (or the sweep is stopping)
        first."""
        head = re.compile(re.escape(f"run {self.name}: ") + r"(.+?)  \(")
        deadline = self.started + START_S
        while not stopping.is_set() and time.monotonic() < deadline:
            with contextlib.suppress(OSError):
                for line in self.log_path.read_text().splitlines():
                    if found := head.match(line):
                        self.run_dir = Path(found.group(1))
                        return self.run_dir
            if self.exited(0.3):
                return None
        return None

    def reports(self) -> Iterator[StatsReport | None]:
        """The run's stats reports as they arrive (``ebrl.watch``) until its launcher exits; None every
        :data:`IDLE_S` without one, so that the caller can check on the sweep."""
        while not self.exited():
            try:
                yield from stats.stream(self.run_dir, idle_timeout=IDLE_S)
            except Exception:  # noqa: BLE001 -- zenoh.ZError: the launcher is not (or no longer) listening
                pass
            yield None
            self.exited(IDLE_S / 4)

    def halt(self) -> int:
        """Stop the run as Ctrl-C does (SIGINT to the launcher's group), then SIGTERM, then SIGKILL; kill anything
        left in its group; reap it. Its exit code."""
        for sig, grace in ((signal.SIGINT, STOP_S), (signal.SIGTERM, TERM_S), (signal.SIGKILL, TERM_S)):
            if self.exited():
                break
            self.signal(sig)
            if self.exited(grace):
                break
        self.signal(signal.SIGKILL)  # what the launcher left in its group (it is unreaped: the group is its own)
        return self.proc.wait()

    def signal(self, sig: int) -> None:
        if self.proc.returncode is None:
            with contextlib.suppress(ProcessLookupError, PermissionError):
                os.killpg(self.proc.pid, sig)

    def failure(self, code: int) -> str:
        """Why the run failed: its summary's failure, else the last lines of its output."""
        with contextlib.suppress(OSError, ValueError, TypeError):
            if why := json.loads((self.run_dir / "summary.json").read_text()).get("failure"):
                return f"ebrl up exited {code}: {why}"
        with contextlib.suppress(OSError):
            lines = [line.strip() for line in self.log_path.read_text().splitlines() if line.strip()]
            return f"ebrl up exited {code}: " + " | ".join(lines[-TAIL:])[-800:]
        return f"ebrl up exited {code}"


def run_trial(trial: Any, config: str, overrides: list[str], name: str, trials_dir: Path, objective: Objective,
              budget: Budget, stopping: threading.Event, cores: list[int] | None = None) -> Outcome:
    """Run one trial to its outcome: start ``ebrl up``, follow its curve (reported to ``trial``), stop it when
    pruned, over ``budget`` or when ``stopping`` is set; always reaped before this returns."""
    run = TrialRun(config, overrides, name, trials_dir, cores)
    run.start()
    curve = Curve(objective)
    why = None
    try:
        if run.wait_run_dir(stopping) is None:
            why = "interrupted" if stopping.is_set() else None
        else:
            why = follow(run, trial, curve, budget, stopping)
    finally:
        code = run.halt()
    return outcome(run, why, code, curve)


def follow(run: TrialRun, trial: Any, curve: Curve, budget: Budget, stopping: threading.Event) -> str | None:
    """Feed the run's reports to ``curve`` and the trial until the run ends (None) or it is to stop:
    ``pruned``, ``budget`` or ``interrupted``."""
    for report in run.reports():
        if stopping.is_set():
            return "interrupted"
        if report is not None:
            curve.feed(report)
            if report_and_check(trial, curve):
                return "pruned"
        if (budget.env_steps and curve.env_steps >= budget.env_steps) or (
                budget.seconds and time.monotonic() - run.started >= budget.seconds):
            return "budget"
    return "interrupted" if stopping.is_set() else None


def outcome(run: TrialRun, why: str | None, code: int, curve: Curve) -> Outcome:
    """What the trial came to, from why it was stopped (None: it ended by itself) and its exit code."""
    done = dict(run_dir=run.run_dir, exit_code=code, step=curve.updates)
    if why == "interrupted":
        return Outcome("interrupted", curve.value(), "the sweep was stopped", **done)
    if why == "pruned":
        return Outcome("pruned", curve.value(), f"pruned at training update {max(curve.points, default=0)}", **done)
    if why is None:
        if run.run_dir is None or code != 0:
            return Outcome("failed", reason=run.failure(code), **done)
        curve = recorded(run.run_dir, curve)
    value = curve.value()
    if value is None:
        return Outcome("failed", reason=curve.missing(), **done)
    return Outcome("complete", value, "over its budget: stopped" if why == "budget" else "", **done)


def recorded(run_dir: Path, live: Curve) -> Curve:
    """The curve from the run's recording (``stats.msgpack``: every report, none missed), where it has points;
    else the one followed live."""
    from ebrl.viz.record import FILENAME, read

    if not (run_dir / FILENAME).is_file():
        return live
    try:
        curve = Curve(live.objective).feed_all(read(run_dir).stats)
    except OSError:
        return live
    return curve if curve.points else live
