"""``sim.core_rebinding = "auto"``: step-level rebinding or whole chunks on pinned cores, chosen by measuring.

Whether rebinding single steps pays depends on the workload and the machine: it balances the cores when
step latencies vary (a long step no longer holds up the envs pinned beside it), and costs a core hand-off
(a wake-up and a migration, tens of µs on a VM) whenever a waiting env goes first. Neither a model of the
step-latency distribution nor a measured hand-off cost alone says which wins once generation, training and
the machine's other load share the cores, so the choice measures the thing itself: a **trial** runs the
sim service's envs in both modes, alternating windows (P R R P P R: each mode as often first as second, so
drift hits both alike), counts env steps per second in each window after a settling time, and keeps
rebinding only if its median beats pinning's by ``margin`` (5 %), or by ``consistent`` (2 %) with every
rebinding window faster than every pinning window (``keep_rebinding``). Ties go to pinning (no hand-offs, no
migrations). The second rule is for heavy-tailed steps of a few ms: rebinding's gain there is real but near
the margin (4 % in 60 s runs of the sweep's ``lat:4:1``), and the median alone kept pinning; when rebinding
gains nothing, its three windows all come out ahead 1 time in 20. The step latencies of every chunk are
watched (the CPU time of each step: the env's own cost, the same whichever mode runs it and whoever shares
its core); a trial runs again when their median or
their tail (p90 / p50) moved by half since the last decision, and every ``recheck_s`` seconds.

Rebinding grants single cores, the paper's greedy algorithm being for single-core workers. An env that keeps
more than one core busy while it steps (a multi-threaded simulator: ``cores_used``, its threads' CPU time over
its steps' wall time, the measure the allocator's profile takes too) is never rebound: the choice is pinned,
and says which ``sim.cores_per_env`` would give each env the cores it uses.

Pure logic over a clock passed in: :class:`ebrl.sched.stepping.RebindingStepping` feeds it each chunk's
results and applies the mode it returns to the core pool.
"""

from __future__ import annotations

import collections
import math
import statistics
from typing import Iterable

import numpy as np

from ebrl.sched.corepool import PINNED, REBIND

NAMES = {PINNED: "pinned", REBIND: "rebind"}
MULTI_THREADED = 1.25  # cores an env keeps busy while stepping above which it counts as multi-threaded
TRIAL_ORDER = (PINNED, REBIND, REBIND, PINNED, PINNED, REBIND)


def keep_rebinding(pinned: list[float], rebind: list[float], margin: float, consistent: float) -> bool:
    """A trial's verdict from its windows' env steps/s: rebinding's median beats pinning's by ``margin``, or by
    ``consistent`` with every rebinding window ahead of every pinning window."""
    gain = statistics.median(rebind) / statistics.median(pinned) if min(pinned, default=0) > 0 else 0.0
    return gain >= 1 + margin or (gain >= 1 + consistent and min(rebind) > max(pinned))


class SteppingChoice:
    def __init__(self, now: float, window_s: float = 2.0, settle_s: float = 0.3, margin: float = 0.05,
                 shift: float = 0.5, recheck_s: float = 300.0, warmup_s: float = 3.0, check_every_s: float = 1.0,
                 consistent: float = 0.02):
        self.window_s, self.settle_s, self.margin, self.consistent = window_s, settle_s, margin, consistent
        self.shift, self.recheck_s = shift, recheck_s
        self.mode = PINNED
        self.trial: list[int] = []  # modes of the windows still to run; empty: decided
        self.rates: dict[int, list[float]] = {PINNED: [], REBIND: []}
        self.window_start = now + warmup_s  # the first trial starts after start-up
        self.window_steps = 0
        self.decided_at = -math.inf
        self.gain = float("nan")  # rebinding's steps/s over pinning's in the last trial
        self.decisions = 0
        self.latencies: collections.deque[float] = collections.deque(maxlen=4000)
        self.chunks: collections.deque[float] = collections.deque(maxlen=200)
        self.env_cores: collections.deque[float] = collections.deque(maxlen=200)  # cores_used per chunk
        self.reference: tuple[float, float] | None = None  # (p50, p90/p50) at the last decision
        self.reason = "start-up"
        self.check_every_s, self._checked_at = check_every_s, -math.inf  # how often to look for a shift
        self._start_trial(now + warmup_s)

    # --- measurements ---------------------------------------------------------------------------------------

    def observe(self, now: float, steps: int, step_s: Iterable[float], chunk_s: float,
                cores_used: float = math.nan) -> None:
        """An env finished its chunk at ``now``: ``steps`` steps, each costing ``step_s`` seconds (CPU), in
        ``chunk_s`` seconds from the chunk's start, keeping ``cores_used`` cores busy while it stepped."""
        self.latencies.extend(step_s)
        self.chunks.append(chunk_s)
        if math.isfinite(cores_used):
            self.env_cores.append(cores_used)
        if self.trial and now >= self.window_start + self.settle():
            self.window_steps += steps

    def settle(self) -> float:
        """Seconds after a switch before steps count (chunks started in the old mode end): a chunk's p50."""
        return max(self.settle_s, statistics.median(self.chunks) if self.chunks else 0.0)

    def window(self) -> float:
        """A window holds at least 8 chunks of every env after settling (slow envs: longer windows; with 4, a
        trial on 16 ms steps measured noise)."""
        return max(self.window_s, self.settle() + 8 * (statistics.median(self.chunks) if self.chunks else 0.0))

    def distribution(self) -> tuple[float, float] | None:
        """(median step latency, p90 / median) of the recent steps; None before 500 were seen."""
        if len(self.latencies) < 500:
            return None
        p50, p90 = np.percentile(np.fromiter(self.latencies, float), [50, 90])
        return float(p50), float(p90 / max(p50, 1e-9))

    def cores_used(self) -> float | None:
        """Median cores an env keeps busy while it steps, over the recent chunks; None before 20 were seen."""
        return statistics.median(self.env_cores) if len(self.env_cores) >= 20 else None

    def multi_threaded(self) -> bool:
        used = self.cores_used()
        return used is not None and used > MULTI_THREADED

    def _multi_threaded_text(self) -> str:
        used = self.cores_used() or 0.0
        return (f"each env keeps {used:.1f} cores busy while it steps, and rebinding grants single cores; "
                f"sim.cores_per_env = {max(2, round(used))} would pin each to that many")

    # --- decisions ----------------------------------------------------------------------------------------

    def tick(self, now: float) -> str | None:
        """Advance the trial or watch for a shift; returns a sentence when the mode was decided (a new
        decision, not a trial window), else None. ``self.mode`` is the mode chunks should run in now."""
        if self.trial:
            if now < self.window_start + self.window():
                return None
            measured = now - self.window_start - self.settle()
            self.rates[self.trial.pop(0)].append(self.window_steps / measured)
            self.window_start, self.window_steps = now, 0
            if self.trial:
                self.mode = self.trial[0]
                return None
            return self._decide(now)
        if now - self._checked_at < self.check_every_s:  # the percentiles cost ~0.1 ms: not after every chunk
            return None
        self._checked_at = now
        if self.multi_threaded():  # no trial: rebinding is not for multi-threaded envs
            if self.mode == REBIND:
                self.mode, self.decided_at, self.decisions = PINNED, now, self.decisions + 1
                return f"pinned: {self._multi_threaded_text()}"
            return None
        why = self._shifted(now)
        if why:
            self._start_trial(now, why)
        return None

    def _start_trial(self, now: float, why: str = "start-up") -> None:
        self.trial = list(TRIAL_ORDER)
        self.rates = {PINNED: [], REBIND: []}
        self.mode, self.window_start, self.window_steps, self.reason = self.trial[0], now, 0, why

    def _decide(self, now: float) -> str:
        pinned, rebind = statistics.median(self.rates[PINNED]), statistics.median(self.rates[REBIND])
        self.gain = rebind / pinned if pinned > 0 else float("nan")
        multi = self.multi_threaded()
        self.mode = REBIND if not multi and keep_rebinding(self.rates[PINNED], self.rates[REBIND], self.margin,
                                                           self.consistent) else PINNED
        self.decided_at, self.decisions = now, self.decisions + 1
        dist = self.distribution()
        dist_text = f"step latency p50 {dist[0] * 1e3:.2f} ms, p90/p50 {dist[1]:.2f}" if dist else "few steps seen"
        self.reference = None  # taken from the next steps
        return (f"{NAMES[self.mode]} ({self.reason}): rebinding ran {self.gain:.2f}x the env steps/s of pinned "
                f"whole chunks ({rebind:.0f} vs {pinned:.0f}; {dist_text})"
                + (f"; {self._multi_threaded_text()}" if multi else ""))

    def _shifted(self, now: float) -> str:
        if now - self.decided_at >= self.recheck_s:
            return f"re-check after {self.recheck_s:.0f} s"
        current = self.distribution()
        if current is None:
            return ""
        if self.reference is None:
            self.reference = current
            return ""
        (p50, tail), (p50_ref, tail_ref) = current, self.reference
        # moved by half, and by more than timer noise (microsecond steps jitter by tens of µs)
        if abs(math.log(p50 / p50_ref)) > math.log(1 + self.shift) and abs(p50 - p50_ref) > 50e-6:
            return f"step latency p50 moved {p50_ref * 1e3:.2f} -> {p50 * 1e3:.2f} ms"
        if abs(math.log(tail / tail_ref)) > math.log(1 + self.shift):
            return f"step latency tail (p90/p50) moved {tail_ref:.2f} -> {tail:.2f}"
        return ""

    def metrics(self) -> dict[str, float]:
        out = {"sim/core_rebinding": float(self.mode == REBIND), "sim/stepping_trial": float(bool(self.trial)),
               "sim/stepping_decisions": float(self.decisions)}
        if not math.isnan(self.gain):
            out["sim/rebinding_gain"] = self.gain
        if (dist := self.distribution()) is not None:
            out["sim/step_latency_p50_ms"] = dist[0] * 1e3
            out["sim/step_latency_p90_ms"] = dist[0] * dist[1] * 1e3
        return out
