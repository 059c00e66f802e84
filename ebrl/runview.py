"""The run as the launcher shows it: the services' stats reports in; the progress line, summary.json and the report out.

Pure apart from writing its files: a :class:`RunView` is fed ``StatsReport``
objects (``ebrl/stats/<run>/<service>/<instance>``) and answers the questions the
launcher asks (the policy version reached, a metric over every instance, the
mean return); :class:`Console` prints, rewriting the progress line in place on
a terminal and every ``PROGRESS_EVERY_S`` seconds otherwise.

The run's numbers (return, success rate, env steps, episodes, segments, their rates) are training's: what it
received and checked (shared/DESIGN.md section 2: the simulator runs the user's env code, and its reports are its
own word). The simulators' own numbers are kept apart, as theirs (``summary.json``'s ``sim``).
"""

from __future__ import annotations

import dataclasses
import json
import math
import os
import shutil
import threading
import time
from collections import deque
from pathlib import Path
from typing import Any, Callable, TextIO

from ebrl import durable
from ebrl import graph
from ebrl.messages import RETURN_WINDOW, StatsReport
from ebrl.weights import plausible

PROGRESS_EVERY_S = 5.0  # a progress line this often when the output is not a terminal
RETURN = "sim/episode_return_mean"  # the simulators' own word: shown as theirs, never as the run's
TRAIN_RETURN, TRAIN_SUCCESS = "train/episode_return_mean", "train/success_rate"  # what a run ends on
# training's cumulative counts (train/0's report) that the run's numbers come from; each restarts from 0 with a
# restarted trainer, which RunView carries over (``train_count``)
TRAIN_COUNTS = ("train/env_steps", "train/episodes", "train/segments_received")
# counters whose movement the stall watch reads (ebrl.stall), tracked over every report, not only the latest
COUNTERS = frozenset({"sim/env_steps", "gen/envs_served", "gen/groups_served", "train/updates",
                      "train/segments_received", "train/env_steps"})
GROUP_SEGMENTS = "train/segments_g"  # + a group: segments training decoded from that group (taken or refused)
RECENT_VALUES = 8  # a counter moved when a report brings a value not among its last this many distinct ones
RATE_WINDOW_S = 10.0  # the progress line's env steps/s and traj/s: training's counts over this many seconds


@dataclasses.dataclass(frozen=True)
class TargetReached:
    """When the mean return first reached ``run.target_return`` (or the success rate ``run.target_success``)."""

    iteration: int
    wall_s: float
    mean_return: float | None
    success_rate: float | None = None


class Movement:
    """Per report key and watched counter, the reports that moved it: that brought a value not among its last
    ``RECENT_VALUES`` distinct ones (the first value seen is where it starts, no move). Frozen reports repeat a
    value, so a flood of them neither hides the real reports' movement in between nor makes a stuck counter look
    moving."""

    def __init__(self) -> None:
        self.moves: dict[tuple[str, str], int] = {}  # (key, counter) -> reports that moved it
        self._recent: dict[tuple[str, str], deque[float]] = {}  # (key, counter) -> its latest distinct values

    def note(self, key: str, name: str, value: float) -> None:
        recent = self._recent.setdefault((key, name), deque(maxlen=RECENT_VALUES))
        if value in recent:
            recent.remove(value)  # the most recently seen last: a repeated value stays known
        elif recent:
            self.moves[(key, name)] = self.moves.get((key, name), 0) + 1
        recent.append(value)


class TrainingCounts:
    """Training's cumulative counts (``TRAIN_COUNTS``, train/0's report) over the run: a restarted trainer counts
    from 0 again (a value below the last one), and the counts before it are carried over, so the run's env steps,
    episodes and segments neither drop nor jump; and the samples the progress line's rates come from."""

    def __init__(self, clock: Callable[[], float]):
        self.clock = clock
        self._counts: dict[str, tuple[float, float]] = {}  # count -> (before the latest restart, latest)
        self._samples: deque[tuple[float, float, float]] = deque()  # (time, env steps, segments)

    def update(self, metrics: dict[str, float]) -> None:
        for name in TRAIN_COUNTS:
            if name in metrics:
                before, last = self._counts.get(name, (0.0, 0.0))
                self._counts[name] = (before + last if metrics[name] < last else before, metrics[name])
        if "train/env_steps" in metrics or "train/segments_received" in metrics:
            now = self.clock()
            self._samples.append((now, self.count("train/env_steps") or 0.0,
                                  self.count("train/segments_received") or 0.0))
            while len(self._samples) > 2 and self._samples[1][0] <= now - RATE_WINDOW_S:
                self._samples.popleft()  # the oldest kept is the last one at or before the window's start

    def count(self, name: str) -> float | None:
        """``name`` over the run; None before training reported it."""
        if name not in self._counts:
            return None
        before, last = self._counts[name]
        return before + last

    def rates(self) -> tuple[float, float] | None:
        """(env steps/s, segments/s) over the last ``RATE_WINDOW_S`` s (0 when the latest report is older than
        that); None before training reported env steps or segments."""
        if not self._samples:
            return None
        (t0, steps0, segs0), (t1, steps1, segs1) = self._samples[0], self._samples[-1]
        if t1 <= t0 or self.clock() - t1 > RATE_WINDOW_S:
            return 0.0, 0.0
        return (steps1 - steps0) / (t1 - t0), (segs1 - segs0) / (t1 - t0)


def may_end(run: Any, version: int, trained: dict[str, float]) -> bool:
    """Whether training's ``version`` and its return and success rate (``trained``: its report's metrics) reach
    ``run.iterations`` or the run's target (``run``: the ``[run]`` section): what the launcher ends a run on
    (:meth:`RunView.iterations_done`, :meth:`RunView.target_reached`). Training asks it after each update, to
    report such an update at once."""
    return bool(run.iterations and version >= run.iterations) or target_met(run, trained) is not None


def target_met(run: Any, trained: dict[str, float]) -> str | None:
    """Which of the run's targets (``run.target_return``, ``run.target_success``) training's metrics
    ``trained`` reach: ``"return"``, ``"success"`` or None."""
    ret, success = trained.get(TRAIN_RETURN), trained.get(TRAIN_SUCCESS)
    if run.target_return is not None and ret is not None and ret >= run.target_return:
        return "return"
    if run.target_success is not None and success is not None and success >= run.target_success:
        return "success"
    return None


def stats_key(run: str, service: str, instance: int | str) -> str | None:
    """The key instance ``service/instance`` of run ``run`` reports on (its role's stats flow in the graph; a name
    the graph lacks as any service's would); None for a role that reports no stats (an observer)."""
    try:
        return graph.keys_of(run, service, instance, service=True).put("stats")
    except ValueError:
        return None


class RunView:
    """The latest stats report of every service instance, and what the launcher reads from them.

    Only reports of the run's own instances count: ``instances(role, instance)`` says whether the run has that
    instance (the launcher: the ones started, or live on another host); a report on another key than its
    own, from an instance the run does not have, or of a value that is not finite (that value; the whole report
    where no value is left) is dropped and counted in ``refused``; so is a training report whose policy version
    runs implausibly far ahead of the last one (:func:`ebrl.weights.plausible`), so a forged report can neither
    end the run nor move its progress.

    ``run.target_return`` and ``run.target_success`` are read from training's reports alone (the return and
    success rate of the latest episodes of the segments it took, which it checked), never from a simulator's:
    on the bus only training's identity may send them. A return that moves further than the episodes finished
    since the last report could move it (each returns at most ``max_abs_reward`` per step) is not taken
    (``returns_refused``). The progress line, ``summary.json`` and its end line take the return, success rate,
    env steps, episodes and segments from training too (``train_count``, ``trained``); the simulators' own
    numbers go into the summary as theirs (``sim``), so a simulator that reports 1e9 moves none of the run's.

    For the stall watch, ``moves`` counts, per report key and watched counter (``COUNTERS``, training's
    per-group segments), the reports that brought a value that counter did not have among its last
    ``RECENT_VALUES`` distinct ones: movement seen in any report, not only in the latest one, which a flood of
    frozen reports on the same key would stand in for at every look (and which cannot fake movement by
    repeating itself)."""

    def __init__(self, run: str, iterations: int = 0, target_return: float | None = None,
                 instances: Callable[[str, int], bool] | None = None, floor: int = 0,
                 target_success: float | None = None, max_abs_reward: float = math.inf,
                 clock: Callable[[], float] = time.monotonic):
        self.run, self.iterations, self.target_return = run, iterations, target_return
        self.clock = clock
        self.target_success, self.max_abs_reward = target_success, max_abs_reward
        self.trained: dict[str, float] = {}  # training's episodes, return, success rate: what the run ends on
        self.returns_refused = 0
        self.instances, self.floor = instances, max(0, floor)  # floor: the newest version known at the start
        self.refused = 0  # reports (or values) not taken
        self._train_version: dict[str, tuple[float, float]] = {}  # train key -> (version, monotonic time)
        self.stats: dict[str, StatsReport] = {}  # key -> latest report
        self.gone: set[str] = set()  # keys of instances that left the bus since their latest report (left())
        self.received: dict[str, int] = {}  # key -> reports taken from it (the stall watch: did one arrive?)
        self.movement = Movement()  # the watched counters' moves, over every report (the stall watch)
        self.training = TrainingCounts(clock)  # training's counts across its restarts, and their rates
        # the eval service's latest result: its periodic reports (eval/busy, ...) do not repeat it
        self.last_eval_metrics: dict[str, float] | None = None
        self.best_return: float | None = None
        self.started = clock()
        self.reached: TargetReached | None = None
        self.note: str | None = None  # what the progress line says first (a stall being acted on: ebrl.stall)

    def on_report(self, key: str, report: StatsReport) -> None:
        if key != stats_key(self.run, report.service, report.instance) or (
                self.instances is not None and not self.instances(report.service, report.instance)):
            self.refused += 1
            return
        finite = {name: value for name, value in report.metrics.items() if math.isfinite(value)}
        if len(finite) < len(report.metrics):
            self.refused += 1
            if not finite:  # nothing left to take: it must not stand in for the instance's last real report
                return
            report = dataclasses.replace(report, metrics=finite)
        if report.service == "train" and "train/policy_version" in finite:
            version, now = finite["train/policy_version"], self.clock()
            last, since = self._train_version.get(key, (float(self.floor), self.started))
            if not plausible(int(version), int(last), now - since):
                self.refused += 1
                return
            self._train_version[key] = (version, now)
        if key == stats_key(self.run, "train", 0):
            if TRAIN_RETURN in finite:
                if self._moves_plausibly(finite):
                    self.trained = {n: finite[n] for n in ("train/episodes", TRAIN_RETURN, TRAIN_SUCCESS)
                                    if n in finite}
                    ret = finite[TRAIN_RETURN]
                    self.best_return = ret if self.best_return is None else max(self.best_return, ret)
                else:
                    self.returns_refused += 1
            self.training.update(finite)
        self.stats[key] = report
        self.gone.discard(key)
        self.received[key] = self.received.get(key, 0) + 1
        for name, value in finite.items():
            if name in COUNTERS or name.startswith(GROUP_SEGMENTS):
                self.movement.note(key, name, value)
        if report.service == "eval" and "eval/version" in report.metrics:
            self.last_eval_metrics = report.metrics

    @property
    def moves(self) -> dict[tuple[str, str], int]:
        """(report key, counter) -> the reports that moved it (:class:`Movement`; the stall watch reads it)."""
        return self.movement.moves

    def train_count(self, name: str) -> float | None:
        """Training's count ``name`` (``TRAIN_COUNTS``) over the run, across restarts of train; None before
        training reported it."""
        return self.training.count(name)

    def train_rates(self) -> tuple[float, float] | None:
        """(env steps/s, segments/s) that training received over the last ``RATE_WINDOW_S`` s."""
        return self.training.rates()

    def _moves_plausibly(self, metrics: dict[str, float]) -> bool:
        """Whether training's return and success rate moved no further than the episodes finished since its
        last report taken could move a mean of the latest ``RETURN_WINDOW`` (a trainer that started again counts
        from 0: its first report is taken as a first)."""
        bound = self.max_abs_reward * max(1.0, metrics.get("train/episode_length_max", 1.0))
        ret, episodes = metrics[TRAIN_RETURN], metrics.get("train/episodes", 0.0)
        if abs(ret) > bound * (1 + 1e-6):
            return False
        before = self.trained
        if not before or episodes < before.get("train/episodes", 0.0):
            return True
        share = min(episodes - before.get("train/episodes", 0.0), RETURN_WINDOW) / RETURN_WINDOW
        moved = abs(ret - before[TRAIN_RETURN]) <= share * 2 * bound * (1 + 1e-6) + 1e-9 * abs(ret)
        success, was = metrics.get(TRAIN_SUCCESS), before.get(TRAIN_SUCCESS)
        return moved and (success is None or was is None or abs(success - was) <= share + 1e-9)

    def left(self, service: str, instance: int | str) -> None:
        """Instance ``service/instance`` left the bus (its token vanished: its process or its host is gone): its
        rates (``*_per_s``) count no more until it reports again; its counts stay (what it did, it did)."""
        self.gone.add(stats_key(self.run, service, instance))

    def metric(self, name: str, how: str = "sum") -> float | None:
        """``name`` over every instance that reports it (sum, max or mean; a rate only of those still on the bus:
        :meth:`left`); None when none does."""
        rate = name.endswith("_per_s")
        values = [r.metrics[name] for key, r in self.stats.items()
                  if name in r.metrics and not (rate and key in self.gone)]
        if not values:
            return None
        return sum(values) if how == "sum" else (max(values) if how == "max" else sum(values) / len(values))

    def version(self) -> int:
        """Training iterations done: the newest policy version published."""
        return int(self.metric("train/policy_version", "max") or 0)

    def version_floor(self) -> int:
        """The newest policy version anyone uses (a restarted train starts past it)."""
        return max(self.version(), int(self.metric("gen/policy_version", "max") or 0))

    def mean_return(self) -> float | None:
        """The run's mean return: training's, of the latest episodes it took (checked); None before one."""
        return self.trained.get(TRAIN_RETURN)

    def success_rate(self) -> float | None:
        """The run's success rate: training's, of the latest episodes it took; None where none reported one."""
        return self.trained.get(TRAIN_SUCCESS)

    def iterations_done(self) -> bool:
        return bool(self.iterations) and self.version() >= self.iterations

    def target_reached(self, wall_s: float) -> str | None:
        """``run.target_return`` or ``run.target_success`` reached now by training's return or success rate
        (remembered for the summary): the line that says so; else None."""
        met = target_met(self, self.trained)
        if met is None:
            return None
        ret, success = self.trained.get(TRAIN_RETURN), self.trained.get(TRAIN_SUCCESS)
        self.reached = TargetReached(self.version(), wall_s, ret, success)
        what = f"run.target_return = {self.target_return:g}: mean return {ret:.1f}" if met == "return" else \
            f"run.target_success = {self.target_success:g}: success rate {success:.0%}"
        return f"reached {what} at iteration {self.reached.iteration} after {wall_s:.0f} s"

    def progress(self, wall_s: float, restarts: int = 0, hosts: int | None = None) -> "Progress":
        """Where the run is: iterations done of ``run.iterations``, and the fields after them."""
        ret, success = self.mean_return(), self.success_rate()
        fields = [  # what matters most first: a narrow terminal cuts the end
            *([self.note] if self.note else []),
            f"return {ret:.1f}" if ret is not None else "return -",
            *([f"success {success:.0%}"] if success is not None else []),
            *([self.last_eval()] if self.last_eval() else []),
            *self._rate_fields(),
            f"policy v{max(int(self.metric('gen/policy_version', 'max') or 0), 0)}",
            f"staleness {self.metric('train/staleness_mean', 'mean') or 0:.2f}",
            *([f"restarts {restarts}"] if restarts else []),
            *([f"hosts {hosts}"] if hosts is not None else []),
        ]
        return Progress(self.version(), self.iterations or None, wall_s, " | ".join(fields))

    def _rate_fields(self) -> list[str]:
        """``1,500 env steps/s | 45.8 traj/s``: what training received. A trainer that does not report its env
        steps (an older one) leaves the simulators' own rate, labelled as theirs (``sim 1,500 env steps/s``)."""
        rates = self.train_rates() if self.training.count("train/env_steps") is not None else None
        if rates is None and (sim := self.metric("sim/env_steps_per_s")) is not None:
            return [f"sim {sim:,.0f} env steps/s", f"sim {self.metric('sim/segments_per_s') or 0:,.1f} traj/s"]
        steps, segments = rates or (0.0, 0.0)
        return [f"{steps:,.0f} env steps/s", f"{segments:,.1f} traj/s"]

    def last_eval(self) -> str | None:
        """``eval v40: success 80% [62-91%], return 512.3`` from the eval service's latest report; None before."""
        return None if self.last_eval_metrics is None else eval_field(self.last_eval_metrics)

    def evaluated_version(self) -> int | None:
        """The policy version of the eval service's latest result; None before one."""
        return None if self.last_eval_metrics is None else int(self.last_eval_metrics["eval/version"])

    def progress_line(self, wall_s: float, restarts: int = 0, hosts: int | None = None) -> str:
        """The progress as one plain line (what a log file gets)."""
        return self.progress(wall_s, restarts, hosts).line()


def eval_field(m: dict[str, float]) -> str:
    """``eval v40: success 80% [62-91%], return 512.3``: an eval service's result on the progress line."""
    parts = []
    if "eval/success_rate" in m:
        interval = (f" [{m['eval/success_rate_lo']:.0%}-{m['eval/success_rate_hi']:.0%}]"
                    if "eval/success_rate_lo" in m and "eval/success_rate_hi" in m else "")
        parts.append(f"success {m['eval/success_rate']:.0%}{interval}")
    if "eval/return" in m:
        parts.append(f"return {m['eval/return']:.1f}")
    return f"eval v{int(m['eval/version'])}: " + ", ".join(parts or ["-"])


def summary(view: RunView, code: int, wall_s: float, *, run_dir: Path, failure: str | None, restarts: dict[str, int],
            host: int, hosts: list[int]) -> dict[str, Any]:
    """The content of ``summary.json`` of the run ``view`` shows: the run's numbers from training (what it received
    and checked), the simulators' own under ``sim`` (their word: not checked, never the run's)."""
    steps = view.train_count("train/env_steps") or 0
    return {
        "run": view.run,
        "run_dir": str(run_dir),
        "exit_code": code,
        "failure": failure,
        "iterations": view.version(),
        "wall_s": round(wall_s, 2),
        "env_steps": int(steps),
        "env_steps_per_s": round(steps / wall_s, 1) if wall_s > 0 else 0.0,
        "segments": int(view.train_count("train/segments_received") or 0),
        "episodes": int(view.train_count("train/episodes") or 0),
        "final_return": view.mean_return(),
        "best_return": view.best_return,
        "final_success_rate": view.success_rate(),
        "target_return": view.target_return,
        "target_success": view.target_success,
        "last_eval": view.last_eval_metrics,  # the eval service's latest result (eval/*), if it ran
        "restarts": restarts,
        "host": host,
        "hosts": hosts,  # every host that took part
        "target_reached": None if view.reached is None else
        {"iteration": view.reached.iteration, "wall_s": round(view.reached.wall_s, 2),
         "return": view.reached.mean_return, "success_rate": view.reached.success_rate},
        "sim": sim_numbers(view),
    }

def sim_numbers(view: RunView) -> dict[str, Any]:
    """What the simulators say of themselves (their latest reports; env steps, episodes and segments summed
    over instances, return and success rate averaged): the user's env code's own word, for comparison with
    training's numbers, never taken as the run's."""
    def number(name: str, how: str = "sum") -> float | None:
        value = view.metric(name, how)
        return None if value is None else round(value, 3)

    return {"env_steps": number("sim/env_steps"), "episodes": number("sim/episodes"),
            "segments": number("sim/segments"), "episode_return_mean": number(RETURN, "mean"),
            "success_rate": number("sim/success_rate", "mean"), "env_steps_per_s": number("sim/env_steps_per_s")}


def write_summary(summary: dict[str, Any], path: Path) -> str:
    """Write ``summary.json`` (``ebrl.durable``); return the line that ends the launcher's output."""
    durable.write_text(path, json.dumps(summary, indent=2) + "\n")
    final = f"{summary['final_return']:.1f}" if summary["final_return"] is not None else "-"
    best = f"{summary['best_return']:.1f}" if summary["best_return"] is not None else "-"
    return (f"run {summary['run']} {'finished' if summary['exit_code'] == 0 else 'stopped'}: "
            f"{summary['iterations']} iterations in {summary['wall_s']:.0f} s, {summary['env_steps']:,} env steps "
            f"({summary['env_steps_per_s']:,.0f}/s), mean return {final} (best {best}); summary in {path}")


def warm_report() -> None:
    """Import what the report draws with, on a thread (``ebrl.viz.report.warm_up``): the launcher starts it as the
    services stop, and :func:`write_report` after them takes that much less."""
    from ebrl.viz import report

    threading.Thread(target=report.warm_up, name="report-imports", daemon=True).start()


def write_report(run_dir: Path) -> str:
    """The headless report of the run (``ebrl report``) from its recording; the line that says where it is, or why
    there is none (a report is a convenience: it never fails the run)."""
    from ebrl.viz import report

    try:
        paths = report.write(run_dir)
    except Exception as exc:
        return f"ebrl: no report: {exc}"
    curves = f", learning curves: {paths['learning']}" if "learning" in paths else ""
    return f"report: {paths['markdown']} (Gantt: {paths['gantt']}{curves})"


@dataclasses.dataclass(frozen=True)
class Progress:
    """Training iterations done (``n`` of ``total``; None: until Ctrl-C) after ``wall_s`` seconds, and the run's
    other numbers (``fields``)."""

    n: int
    total: int | None
    wall_s: float
    fields: str

    def line(self) -> str:
        """``iter 4/10 (40%) | 0:01:02<0:01:33, 15.6 s/it | 1,500 env steps/s | ...``: tqdm's percentage, ETA and
        rate, without the bar."""
        from tqdm import tqdm

        head = "{desc} {n_fmt}/{total_fmt} ({percentage:.0f}%) | {elapsed}<{remaining}, {rate_fmt}" if self.total \
            else "{desc} {n_fmt} | {elapsed}, {rate_fmt}"
        meter = tqdm.format_meter(min(self.n, self.total or self.n), self.total, self.wall_s, prefix="iter",
                                  unit="it", bar_format=head)
        return f"{meter} | {self.fields}"


class Console:
    """The launcher's output: whole lines, and the progress: a tqdm bar on a terminal (percentage, ETA, rate, the
    run's numbers; redrawn in place, cut to the terminal's width), a plain line every ``PROGRESS_EVERY_S``
    seconds otherwise (a log stays readable)."""

    def __init__(self, out: TextIO):
        self.out = out
        self.tty = hasattr(out, "isatty") and out.isatty()
        self._last_progress = 0.0
        self._bar: Any = None

    def say(self, text: str) -> None:
        if self._bar is not None:
            self._bar.clear()
            print(text.lstrip("\n"), file=self.out, flush=True)
            self._bar.refresh()
            return
        if self.tty:
            text = "\r\033[K" + text.lstrip("\n")
        print(text, file=self.out, flush=True)

    def progress(self, progress: Progress, force: bool = False) -> None:
        if self.tty:
            self._draw(progress)
        elif force or time.monotonic() - self._last_progress >= PROGRESS_EVERY_S:
            self.say(progress.line())
            self._last_progress = time.monotonic()

    def _draw(self, progress: Progress) -> None:
        from tqdm import tqdm

        if self._bar is None or self._bar.total != progress.total:
            if self._bar is not None:
                self._bar.close()
            fmt = ("{desc} {n_fmt}/{total_fmt} {percentage:3.0f}%|{bar}| {elapsed}<{remaining}, {rate_fmt}{postfix}"
                   if progress.total else "{desc} {n_fmt} | {elapsed}, {rate_fmt}{postfix}")
            done = min(progress.n, progress.total or progress.n)  # a resumed run: iterations done before
            self._bar = tqdm(total=progress.total, initial=done, desc="iter", unit="it", file=self.out,
                             ncols=self.width(), nrows=24, bar_format=fmt, mininterval=0, leave=True)
            self._bar.start_t = self._bar._time() - progress.wall_s  # the run's clock, not the bar's
        done = min(progress.n, progress.total or progress.n)
        self._bar.ncols = self.width()  # the terminal may have been resized
        if done > self._bar.n:
            self._bar.update(done - self._bar.n)
        self._bar.set_postfix_str(progress.fields, refresh=False)
        self._bar.refresh()

    def width(self) -> int:
        """The terminal's columns now (a terminal that says 0, e.g. under `script`, counts as 120 wide; tqdm would
        draw nothing there, as it does on a terminal 0 rows high: hence nrows=24 too)."""
        try:
            columns = os.get_terminal_size(self.out.fileno()).columns
        except (AttributeError, OSError, ValueError):
            columns = 0
        return columns or shutil.get_terminal_size((120, 24)).columns or 120

    def end_progress(self) -> None:
        """Leave the line the progress was drawing (before the shutdown's lines)."""
        if self._bar is not None:
            self._bar.close()
            self._bar = None
        elif self.tty:
            self.out.write("\n")
