"""The launcher's stall watch: a run that stops moving is said, by stage and why, and acted on -- never a progress
line that stands still in silence.

It reads what every service reports (:class:`~ebrl.runview.RunView`) and finds, within ``run.stall_timeout``
seconds, the first of these that holds (each stage is watched from its first progress on, so a slow start --
kernels compiling, a simulator loading -- is not a stall):

* an instance of sim, gen or train sent no stats report for that long: its process is stopped or hung;
* a sim instance made no env steps: gen answered nothing in that time either -- if gen holds observations that
  need a newer policy and train, with a full batch, made no update and uses next to no CPU, train is the one
  stuck; without a batch, the segments do not reach it (the sim); while it computes, a long update is no
  stall; else gen -- or gen answers and the sim itself is stuck;
* train made no update for that long (and 3x its last update's time) with a full batch while segments kept
  coming and its process used next to no CPU: it waits on something that will not come (not an attack that
  keeps its batch from filling: that is no stall of train's).

The launcher (``ebrl.launch``) shows the stall on the progress line and in the run's events, kills the stuck
instance's process group so that the supervisor starts it again (a restart like any other, counted against
``run.max_restarts``), and ends the run with a clear failure if the same stage stalls again within
``AGAIN_S_FACTOR`` x the timeout of its restart.
"""

from __future__ import annotations

import time
from dataclasses import dataclass
from typing import TYPE_CHECKING, Callable

if TYPE_CHECKING:
    from ebrl.runview import RunView
    from ebrl.supervisor import Supervisor

WATCHED = ("sim", "gen", "train")
PROGRESS = {"sim": "sim/env_steps", "gen": "gen/envs_served", "train": "train/updates"}
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
    """Feed it the run's view every few tenths of a second (:meth:`check`); ``timeout_s`` <= 0 turns it off."""

    def __init__(self, timeout_s: float, clock=time.monotonic):
        self.timeout, self.clock = timeout_s, clock
        self.moved: dict[tuple[str, str], tuple[float, float]] = {}  # (report key, counter) -> (value, changed at)
        self.first: dict[tuple[str, str], float] = {}  # (report key, counter) -> its value before it ever changed
        self.arrived: dict[str, float] = {}  # report key -> when its latest report arrived
        self.seen: dict[str, int] = {}  # report key -> how many reports the view had taken from it (``received``)
        self.quiet_until = 0.0  # after an action: the restarted service's start is not a stall
        self.acted: dict[str, float] = {}  # service -> when the watch last restarted it
        self.shown: Stall | None = None  # the stall acted on, until env steps move again

    def check(self, view: RunView, judge: set[str] | None = None) -> Stall | None:
        """The first stall found now, or None. ``judge``: the instances (``"gen/0"``) to judge now (this host's,
        running, not just started); None: all."""
        now = self.clock()
        self._observe(view, now)
        if self.timeout <= 0 or now < self.quiet_until:
            return None
        reports = {key: r for key, r in view.stats.items()
                   if r.service in WATCHED and (judge is None or f"{r.service}/{r.instance}" in judge)}
        for key, report in reports.items():
            silent = now - self.arrived.get(key, now)
            if silent > self.timeout:
                return Stall(f"{report.service}/{report.instance}",
                             f"no stats report for {silent:.0f} s: its process is stopped or hung")
        idle = {key: now - self.moved[(key, PROGRESS[r.service])][1] for key, r in reports.items()
                if (key, PROGRESS[r.service]) in self.moved}

        def stuck(role: str) -> list[str]:
            return [key for key, r in reports.items() if r.service == role and idle.get(key, 0.0) > self.timeout]

        def name(key: str) -> str:
            r = reports[key]
            return f"{r.service}/{r.instance}"

        def waits(key: str) -> bool:  # a train with a full batch that makes no update and computes none
            r = reports[key]
            return idle[key] > 3 * r.metrics.get("train/update_s", 0.0) and r.metrics.get("train/batch_ready", 1) \
                and r.metrics.get("proc/cpu_percent", 100.0) < IDLE_CPU_PERCENT

        def computes(key: str) -> bool:  # a long update (a mode without overlap waits for it): not a stall
            return reports[key].metrics.get("proc/cpu_percent", 100.0) >= IDLE_CPU_PERCENT

        if sims := stuck("sim"):
            quiet = f"no env steps for {idle[sims[0]]:.0f} s"
            gens = [key for key, r in reports.items() if r.service == "gen"]
            if gens and all(key in stuck("gen") for key in gens):
                waiting = view.metric("gen/obs_waiting_for_policy") or 0
                if waiting and (trains := stuck("train")):
                    if waiting_trains := [key for key in trains if waits(key)]:
                        return Stall(name(waiting_trains[0]), f"{quiet}: generation holds {waiting:.0f} observation(s) "
                                                              f"for a newer policy and train, with a full batch, made "
                                                              f"no update for {idle[trains[0]]:.0f} s, next to no CPU used")
                    if any(computes(key) for key in trains):
                        return None  # a long update: generation waits for it (a mode without overlap)
                    return Stall(name(sims[0]), f"{quiet}: generation holds {waiting:.0f} observation(s) for a newer "
                                                f"policy and train lacks a batch: the segments do not reach it")
                return Stall(name(gens[0]), f"{quiet}: generation answered no observation for {idle[gens[0]]:.0f} s")
            return Stall(name(sims[0]), f"{quiet} while generation answers")
        for key in stuck("train"):
            received = self.moved.get((key, "train/segments_received"))
            if waits(key) and received is not None and received[1] > self.moved[(key, PROGRESS["train"])][1]:
                return Stall(name(key), f"no update for {idle[key]:.0f} s with a full batch while segments came in, "
                                        "and next to no CPU used: it waits on something that does not come")
        return None

    def note(self) -> str | None:
        """What the progress line says while a stall is being acted on (until env steps move again)."""
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
        self.moved = {k: (value, self.quiet_until) for k, (value, _) in self.moved.items()}
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
            for counter in (PROGRESS[report.service], "train/segments_received"):
                value = report.metrics.get(counter)
                if value is None:
                    continue
                last = self.moved.get((key, counter))
                first = self.first.setdefault((key, counter), value)  # watched from its first change on
                if value != (first if last is None else last[0]):
                    self.moved[(key, counter)] = (value, now)
                    if last is not None and counter == PROGRESS["sim"] and now >= self.quiet_until:
                        self.shown = None  # the run moves again


def watch(stalls: StallWatch, view: RunView, supervisor: Supervisor, say: Callable[[str], None],
          event: Callable[[str, str], None]) -> str | None:
    """One look (the launcher's loop): a stall found is said (its line, an event, the progress line) and its
    instance killed, for the supervisor to start again; returns the run's failure where that did not help
    before, else None."""
    if view.iterations_done():  # train idles by design from here on
        return None
    now = stalls.clock()
    judge = {c.name for c in supervisor.children  # this host's, running, started long enough ago
             if not c.given_up and c.restart_at is None and c.running() and now - c.started >= stalls.timeout}
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
