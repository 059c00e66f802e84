"""The launcher's stall watch: a run that stops moving is said, by stage and why, and acted on -- never a progress
line that stands still in silence.

It reads what every service reports (:class:`~ebrl.runview.RunView`) and finds, within ``run.stall_timeout``
seconds, the first of these that holds (each stage is watched from its first progress on, so a slow start --
kernels compiling, a simulator loading -- is not a stall):

* an instance of gen or train sent no stats report for that long: its process is stopped or hung; so did a sim
  instance whose segments stopped reaching training too (one whose data keeps arriving is no stall);
* no segments from a sim instance reached training for that long. The simulator runs the user's env code, so
  it is judged on what the others saw of it (shared/DESIGN.md section 2), never on its own reports: training's
  counts of the segments it decoded from that instance's groups (``train/segments_g<group>``; the groups of
  ``sim/<n>`` are ``n * groups_per_sim ...``, ``ebrl.sched.fleet``), or, from a trainer without those, of all
  it received (``train/segments_received``, ``train/env_steps``), and generation's answers. Then: where the
  other simulators' segments arrive, that instance is stuck; where gen answered nothing in that time either
  -- if gen holds observations that need a newer policy and train, with a full batch, made no update and
  uses next to no CPU, train is the one stuck; without a batch, the segments do not reach it (the sim);
  while it computes, a long update is no stall; gen holding observations it does not answer is stuck; gen
  holding none, the simulators send none (the sim). Where gen answers, the sims' observations reach it: no
  stall, unless one of several simulators' own env steps stopped too (that one is named). On a host that
  simulates for another's training, no simulator is judged while training's or generation's reports do not
  reach it at all: the link between the hosts is down, and the host stops once the primary is gone
  (``ebrl.hosts.PRIMARY_LOST_S``), not the simulator;
* train made no update for that long (and 3x its last update's time) with a full batch while segments kept
  coming and its process used next to no CPU: it waits on something that will not come (not an attack that
  keeps its batch from filling: that is no stall of train's).

A counter moved when any report since the last look brought a new value (``RunView.moves``), not when the
latest report differs: a flood of frozen reports on an instance's key (its own credential may send them)
stands in for the real ones at every look, and must neither get a moving stage killed nor make a stuck one
look alive.

The launcher (``ebrl.launch``) shows the stall on the progress line and in the run's events, kills the stuck
instance's process group so that the supervisor starts it again (a restart like any other, counted against
``run.max_restarts``), and ends the run with a clear failure if the same stage stalls again within
``AGAIN_S_FACTOR`` x the timeout of its restart.
"""

from __future__ import annotations

import math
import time
from dataclasses import dataclass
from typing import TYPE_CHECKING, Callable

from ebrl.runview import GROUP_SEGMENTS

if TYPE_CHECKING:
    from ebrl.runview import RunView
    from ebrl.supervisor import Supervisor

WATCHED = ("sim", "gen", "train")
# each stage's own counter: gen's and train's progress; sim's only names which of several simulators stopped
PROGRESS = {"sim": "sim/env_steps", "gen": "gen/envs_served", "train": "train/updates"}
SEGMENTS = "train/segments_received"
RUN_SEGMENTS = (SEGMENTS, "train/env_steps")  # training's counts of every simulator's segments: the run's sims
IDLE_CPU_PERCENT = 5.0  # a train that made no update and used less CPU than this waits, it does not compute
AGAIN_S_FACTOR = 3.0  # the same stage stalled again this soon (x the timeout) after its restart: the run fails


@dataclass(frozen=True)
class Stall:
    """A stuck service instance (``"gen/0"``) and why the watch says so."""

    service: str
    reason: str

    def __str__(self) -> str:
        return f"{self.service} stalled: {self.reason}"


class StallWatch:
    """Feed it the run's view every few tenths of a second (:meth:`check`); ``timeout_s`` <= 0 turns it off.
    ``groups_per_sim``: groups of each sim instance (``sim/<n>`` has ``n * groups_per_sim`` on), which names the
    instance whose segments stopped; None: unknown, the run's sims are judged together."""

    def __init__(self, timeout_s: float, clock=time.monotonic, groups_per_sim: int | None = None):
        self.timeout, self.clock, self.groups_per_sim = timeout_s, clock, groups_per_sim
        self.moved: dict[tuple[str, str], float] = {}  # (report key, counter) -> when it last moved
        self.moves: dict[tuple[str, str], int] = {}  # (report key, counter) -> the view's moves at the last look
        self.arrived: dict[str, float] = {}  # report key -> when its latest report arrived
        self.seen: dict[str, int] = {}  # report key -> how many reports the view had taken from it (``received``)
        self.quiet_until = 0.0  # after an action: the restarted service's start is not a stall
        self.acted: dict[str, float] = {}  # service -> when the watch last restarted it
        self.shown: Stall | None = None  # the stall acted on, until segments reach training again

    def check(self, view: RunView, judge: set[str] | None = None) -> Stall | None:
        """The first stall found now, or None. ``judge``: the instances (``"gen/0"``) to judge now (this host's,
        running, not just started); None: all."""
        now = self.clock()
        self._observe(view, now)
        if self.timeout <= 0 or now < self.quiet_until:
            return None
        reports = {key: r for key, r in view.stats.items()
                   if r.service in WATCHED and (judge is None or f"{r.service}/{r.instance}" in judge)}
        grouped = self.per_group(view)
        fed = {key: self._fed(view, r.instance, grouped) for key, r in view.stats.items() if r.service == "sim"}
        look = _Look(self, view, now, reports, fed, grouped)
        for key, report in reports.items():
            silent = now - self.arrived.get(key, now)
            if silent > self.timeout and (report.service != "sim" or look.fed_idle(key) > self.timeout):
                also = " and no segments of it reached training" if report.service == "sim" else ""
                return Stall(look.name(key), f"no stats report for {silent:.0f} s{also}: its process is stopped or "
                                             "hung")
        if sims := look.stuck("sim"):
            # training's and generation's reports stopped reaching this host, where they run on another: the link
            # to them is down (the secondary host stops once the primary is gone), not this simulator
            return None if look.remote_silent() else look.sims_stalled(sims)
        for key in look.stuck("train"):
            received = self.moved.get((key, SEGMENTS))
            if look.waits(key) and received is not None and received > self.moved[(key, PROGRESS["train"])]:
                return Stall(look.name(key), f"no update for {look.idle[key]:.0f} s with a full batch while segments "
                                             "came in, and next to no CPU used: it waits on something that does not "
                                             "come")
        return None

    def per_group(self, view: RunView) -> bool:
        """Whether sim instances are judged each on its own groups: their number known and training reporting
        its segments per group."""
        return self.groups_per_sim is not None and any(
            name.startswith(GROUP_SEGMENTS) for r in view.stats.values() if r.service == "train" for name in r.metrics)

    def _fed(self, view: RunView, instance: int, grouped: bool) -> float | None:
        """When training last received segments of sim ``instance`` (``grouped``: of its groups; else of any
        simulator); None before it ever did (a simulator starting)."""
        trains = [key for key, r in view.stats.items() if r.service == "train"]
        if grouped:
            first = instance * self.groups_per_sim  # type: ignore[operator]
            counters = [f"{GROUP_SEGMENTS}{g}" for g in range(first, first + self.groups_per_sim)]  # type: ignore
        else:
            counters = list(RUN_SEGMENTS)
        times = [self.moved[(key, c)] for key in trains for c in counters if (key, c) in self.moved]
        return max(times) if times else None

    def note(self) -> str | None:
        """What the progress line says while a stall is being acted on (until segments reach training again)."""
        return None if self.shown is None else f"STALLED {self.shown.service}, restarted"

    def acting(self, stall: Stall) -> bool:
        """The launcher restarts ``stall.service``; False where the watch restarted it a short while ago already
        (the restart did not help: the run should fail)."""
        now = self.clock()
        again = now - self.acted.get(stall.service, -1e18) < AGAIN_S_FACTOR * self.timeout + self.timeout
        self.acted[stall.service] = now
        self.shown = stall
        self.quiet_until = now + self.timeout  # the new instance starts and reports before it is watched again
        # every watched counter and report counts from the end of the quiet time: the new instance's too, which
        # made progress before (it restarts from 0: a change), so a restart that changes nothing is seen again
        self.moved = {k: self.quiet_until for k in self.moved}
        self.arrived = {k: self.quiet_until for k in self.arrived}
        return not again

    def _observe(self, view: RunView, now: float) -> None:
        for key, report in view.stats.items():
            if report.service not in WATCHED:
                continue
            # a count, not the report's seq: on an open bus a forged report may stand in for the real one at the
            # moment of a look, and one with the same seq every time would hide the real ones that came between
            received = view.received.get(key, 0)
            if self.seen.get(key) != received or key not in self.arrived:
                self.seen[key], self.arrived[key] = received, now
        for counter, n in view.moves.items():  # a move in any report since the last look, not only the latest
            if self.moves.get(counter) != n:
                self.moves[counter], self.moved[counter] = n, now
                if now >= self.quiet_until and (counter[1] in RUN_SEGMENTS or counter[1].startswith(GROUP_SEGMENTS)):
                    self.shown = None  # segments reach training again: the run moves


class _Look:
    """One look of the watch at the run: who is idle for how long, and which stage a stall is blamed on."""

    def __init__(self, watch: StallWatch, view: RunView, now: float, reports: dict, fed: dict[str, float | None],
                 grouped: bool):
        self.watch, self.view, self.now, self.reports, self.fed, self.grouped = watch, view, now, reports, fed, grouped
        self.timeout = watch.timeout
        self.every_sim = [key for key, r in view.stats.items() if r.service == "sim"]
        self.idle = {key: now - when for key, r in reports.items()
                     if (when := fed[key] if r.service == "sim" else watch.moved.get((key, PROGRESS[r.service])))
                     is not None}

    def remote_silent(self) -> bool:
        """Training's or generation's reports, where they are not judged here (another host's), stopped arriving."""
        return any(r.service in ("train", "gen") and key not in self.reports
                   and self.now - self.watch.arrived.get(key, self.now) > self.timeout
                   for key, r in self.view.stats.items())

    def fed_idle(self, key: str) -> float:
        """Seconds since training last received segments of this simulator."""
        return math.inf if self.fed[key] is None else self.now - self.fed[key]

    def name(self, key: str) -> str:
        r = self.view.stats[key]
        return f"{r.service}/{r.instance}"

    def stuck(self, role: str) -> list[str]:
        return [key for key, r in self.reports.items() if r.service == role and self.idle.get(key, 0.0) > self.timeout]

    def waits(self, key: str) -> bool:
        """A train with a full batch that makes no update and computes none."""
        r = self.reports[key]
        return self.idle[key] > 3 * r.metrics.get("train/update_s", 0.0) and r.metrics.get("train/batch_ready", 1) \
            and r.metrics.get("proc/cpu_percent", 100.0) < IDLE_CPU_PERCENT

    def computes(self, key: str) -> bool:
        """A long update (a mode without overlap waits for it): not a stall."""
        return self.reports[key].metrics.get("proc/cpu_percent", 100.0) >= IDLE_CPU_PERCENT

    def own_stopped(self, keys: list[str]) -> list[str]:
        """Which of several simulators' own env steps stopped too."""
        moved = self.watch.moved
        return [key for key in keys if self.now - moved.get((key, PROGRESS["sim"]), -math.inf) > self.timeout]

    def sims_stalled(self, sims: list[str]) -> Stall | None:
        """No segments of the simulators ``sims`` reached training: which stage is stuck (module doc), if any."""
        name, idle = self.name, self.idle
        quiet = f"no segments from {name(sims[0])} reached training for {idle[sims[0]]:.0f} s"
        if self.grouped and any(self.fed_idle(key) <= self.timeout for key in self.every_sim if key not in sims):
            return Stall(name(sims[0]), f"{quiet} while the other simulators' segments do")
        gens = [key for key, r in self.reports.items() if r.service == "gen"]
        if gens and all(key in self.stuck("gen") for key in gens):
            waiting = self.view.metric("gen/obs_waiting_for_policy") or 0
            if waiting and (trains := self.stuck("train")):
                if waiting_trains := [key for key in trains if self.waits(key)]:
                    return Stall(name(waiting_trains[0]), f"{quiet}: generation holds {waiting:.0f} observation(s) "
                                                          f"for a newer policy and train, with a full batch, made "
                                                          f"no update for {idle[trains[0]]:.0f} s, next to no CPU used")
                if any(self.computes(key) for key in trains):
                    return None  # a long update: generation waits for it (a mode without overlap)
                return Stall(name(sims[0]), f"{quiet}: generation holds {waiting:.0f} observation(s) for a newer "
                                            f"policy and train lacks a batch: the segments do not reach it")
            if waiting or self.view.metric("gen/obs_queue"):
                return Stall(name(gens[0]), f"{quiet}: generation answered no observation for "
                                            f"{idle[gens[0]]:.0f} s, holding some")
            blamed = (self.own_stopped(sims) or sims)[0]
            return Stall(name(blamed), f"no segments from {name(blamed)} reached training for {idle[blamed]:.0f} s "
                                       "and generation, which answered none, holds no observation: it sends none")
        if len(self.every_sim) > 1 and (named := self.own_stopped(sims)) and len(named) < len(self.every_sim):
            return Stall(name(named[0]), f"no segments from {name(named[0])} reached training for "
                                         f"{idle[named[0]]:.0f} s and its own env steps stopped, while generation "
                                         "answers the others")
        return None  # generation answers: the simulators' observations reach it, their data keeps arriving


def watch(stalls: StallWatch, view: RunView, supervisor: Supervisor, say: Callable[[str], None],
          event: Callable[[str, str], None]) -> str | None:
    """One look (the launcher's loop): a stall found is said (its line, an event, the progress line) and its
    instance killed, for the supervisor to start again; returns the run's failure where that did not help
    before, else None."""
    if view.iterations_done():  # train idles by design from here on
        return None
    now = stalls.clock()
    judge = {name for c in supervisor.children  # this host's, running, started long enough ago
             if not c.given_up and c.restart_at is None and c.running() and now - c.started >= stalls.timeout
             for name in c.names}
    stall = stalls.check(view, judge)
    view.note = stalls.note()
    if stall is None:
        return None
    event("stall", str(stall))
    if not stalls.acting(stall):
        failure = f"{stall}; it stalled again after the restart that should have cleared it"
        say(f"\nebrl: {failure}")
        return failure
    view.note = stalls.note()
    say(f"\nebrl: {stall}; restarting it")
    supervisor.kill(stall.service)
    return None
