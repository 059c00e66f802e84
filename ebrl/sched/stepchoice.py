"""``sim.core_rebinding = "auto"``: step-level rebinding or whole chunks on pinned cores, chosen by measuring
what the run delivers, and chosen again while it runs.

Whether rebinding single steps pays depends on the workload and the machine: it balances the cores when
step latencies vary (a long step no longer holds up the envs pinned beside it), and costs a core hand-off
(a wake-up and a migration, tens of µs on a VM) whenever a waiting env goes first. Neither a model of the
step-latency distribution nor a measured hand-off cost alone says which wins once generation, training and
the machine's other load share the cores, so the choice measures the thing itself: the env steps per second
this sim service completes -- what the whole pipeline delivers, since an env waits for its next actions --
in each mode, in the run's steady state:

* **Not at start-up.** The first trial starts once chunks acted by policy version ``steady_version`` (2)
  arrive (training runs, kernels and caches are warm; at c20bf78 a trial in the first seconds measured
  rebinding 1.10x faster on W1 and the run that kept it delivered 29 % less), or after
  ``steady_timeout_s`` where no such version comes. Until then the envs run pinned whole chunks, which
  never costs much: rebinding first where the step latencies suggested it (long, heavy-tailed steps) was
  tried, and LIBERO's steps (a 195 ms camera render at each chunk's start among 5 ms steps) ran 0.61x the
  best baseline for the 59 % of a 45 s window it spent rebinding before its trial, while on the
  heavy-tailed sweep points it bought nothing measurable (`lat:16:1` 1.17x with it and without).
* **Paired windows, a confidence rule.** A trial runs pairs of windows, one in each mode, the order
  alternating (P R, R P, P R, ...: drift hits both alike); a window spans at least ``window_s``, 8 chunks
  after settling, and the interval between two policy updates (training's share of the cores comes and goes
  with them). Each pair
  gives the log of rebinding's rate over pinning's; after ``min_pairs`` (2) the trial decides as soon as the
  one-sided ``CONFIDENCE`` (95 %) bounds of their mean (Student's t) say rebinding is faster by more than
  ``WORTH`` (1 %: rebinding), or cannot be (pinned); after ``max_pairs`` (8) without that, the point estimate
  decides (rebinding when it is more than ``WORTH`` ahead; pinning, with no hand-offs or migrations, is the
  tie's side). A clear difference is told after two pairs
  (rebinding 29 % slower, windows within 3 %), a small one takes more. (At 97.5 %, W1's trials took 3-4
  pairs to turn down rebinding at 0.91x, each rebinding window costing the run 9 % of its rate; a wrong
  call at 95 % is a small difference, and the watch below undoes a large one.)
* **Kept deciding.** After a decision the chosen mode's windows go on being measured; when the median of
  the last three falls below the other mode's rate in the trial by ``drop`` (5 %), a new trial runs (the
  choice is undone if the other mode now wins). A trial also runs again every ``recheck_s`` seconds and when
  the step latencies (the CPU time of each step: the env's own cost, the same whichever mode runs it) moved:
  their median or their tail (p90 / p50) by half since the last decision.

Rebinding grants single cores, the paper's greedy algorithm being for single-core workers. An env that keeps
more than one core busy while it steps (a multi-threaded simulator: ``cores_used``, its threads' CPU time over
its steps' wall time, the measure the allocator's profile takes too) is never rebound: the choice is pinned,
and says which ``sim.cores_per_env`` would give each env the cores it uses.

Pure logic over a clock passed in: :class:`ebrl.sched.stepping.RebindingStepping` feeds it each chunk's
results and applies the mode it returns to the core pool; the sim fleet tells it the policy versions.
"""

from __future__ import annotations

import collections
import math
import statistics
from typing import Iterable

import numpy as np

from ebrl.resources.corepool import PINNED, REBIND

NAMES = {PINNED: "pinned", REBIND: "rebind"}
MULTI_THREADED = 1.25  # cores an env keeps busy while stepping above which it counts as multi-threaded
CONFIDENCE = 0.95  # one-sided, at each look (after every pair)
# Student's t's CONFIDENCE quantile by degrees of freedom 1-30 (scipy.stats.t.ppf to 6 digits; a test checks them
# for dof 1-200), beyond 30 its Cornish-Fisher expansion around the normal's Z_95 (within 1e-6 there): the simulator's
# process does not import scipy.stats (1.3 s of its start-up, and of the launcher's, on 2 cores)
T_95 = (6.313752, 2.919986, 2.353363, 2.131847, 2.015048, 1.94318, 1.894579, 1.859548, 1.833113, 1.812461, 1.795885,
        1.782288, 1.770933, 1.76131, 1.75305, 1.745884, 1.739607, 1.734064, 1.729133, 1.724718, 1.720743, 1.717144,
        1.713872, 1.710882, 1.708141, 1.705618, 1.703288, 1.701131, 1.699127, 1.697261)
Z_95 = 1.6448536269514722
WORTH = 0.01  # a gain of rebinding below 1 % is not worth its hand-offs: the indifference zone's width


def t_quantile(dof: int) -> float:
    """Student's t's one-sided ``CONFIDENCE`` quantile with ``dof`` degrees of freedom."""
    if dof < 1:
        raise ValueError(f"t_quantile: {dof} degrees of freedom")
    if dof <= len(T_95):
        return T_95[dof - 1]
    z, nu = Z_95, float(dof)
    return (z + (z ** 3 + z) / (4 * nu) + (5 * z ** 5 + 16 * z ** 3 + 3 * z) / (96 * nu ** 2)
            + (3 * z ** 7 + 19 * z ** 5 + 17 * z ** 3 - 15 * z) / (384 * nu ** 3))


def interval(log_ratios: list[float]) -> tuple[float, float, float]:
    """(mean, low, high) of rebinding's rate over pinning's, from the pairs' log ratios: the geometric mean
    and its one-sided ``CONFIDENCE`` bounds (Student's t)."""
    n = len(log_ratios)
    mean = statistics.fmean(log_ratios)
    half = t_quantile(n - 1) * statistics.stdev(log_ratios) / math.sqrt(n) \
        if n > 1 else math.inf
    return math.exp(mean), math.exp(mean - half), math.exp(mean + half)


def verdict(log_ratios: list[float], min_pairs: int) -> int | None:
    """REBIND when rebinding is faster by more than ``WORTH`` at ``CONFIDENCE``, PINNED when it cannot be (its upper
    bound below 1 + ``WORTH``), None while the pairs cannot tell."""
    if len(log_ratios) < max(2, min_pairs):
        return None
    _, low, high = interval(log_ratios)
    return REBIND if low > 1.0 + WORTH else PINNED if high < 1.0 + WORTH else None


class StepWatch:
    """The recent steps and chunks of a sim service's envs: their latency distribution, the cores an env keeps
    busy while it steps, a chunk's typical time."""

    def __init__(self):
        self.latencies: collections.deque[float] = collections.deque(maxlen=4000)
        self.chunks: collections.deque[float] = collections.deque(maxlen=200)
        self.env_cores: collections.deque[float] = collections.deque(maxlen=200)  # cores_used per chunk

    def add(self, step_s: Iterable[float], chunk_s: float, cores_used: float) -> None:
        self.latencies.extend(step_s)
        self.chunks.append(chunk_s)
        if math.isfinite(cores_used):
            self.env_cores.append(cores_used)

    def chunk(self) -> float:
        """A chunk's median seconds (0 before any was seen)."""
        return statistics.median(self.chunks) if self.chunks else 0.0

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

    def multi_threaded_text(self) -> str:
        used = self.cores_used() or 0.0
        return (f"each env keeps {used:.1f} cores busy while it steps, and rebinding grants single cores; "
                f"sim.cores_per_env = {max(2, round(used))} would pin each to that many")


class SteppingChoice:
    def __init__(self, now: float, window_s: float = 2.0, settle_s: float = 0.3, shift: float = 0.5,
                 recheck_s: float = 300.0, warmup_s: float = 3.0, check_every_s: float = 1.0,
                 steady_version: int = 2, steady_timeout_s: float = 60.0, min_pairs: int = 2, max_pairs: int = 8,
                 drop: float = 0.05):
        self.window_s, self.settle_s, self.shift, self.recheck_s = window_s, settle_s, shift, recheck_s
        self.min_pairs, self.max_pairs, self.drop = min_pairs, max_pairs, drop
        self.mode = PINNED
        self.trial = False  # a trial runs: windows alternate between the modes
        self.pairs: list[tuple[float, float]] = []  # (pinned, rebind) env steps/s of the trial's pairs
        self.pending: dict[int, float] = {}  # the current pair's window rates so far, by mode
        self.window_mode = PINNED
        self._new_window(now)
        self.realized: collections.deque[float] = collections.deque(maxlen=3)  # the chosen mode's windows since
        self.other_rate = math.nan  # the mode not chosen: its median rate in the last trial
        self.decided_at = -math.inf
        self.gain = float("nan")  # rebinding's steps/s over pinning's in the last trial (geometric mean)
        self.decisions = 0
        self.steps = StepWatch()
        self.reference: tuple[float, float] | None = None  # (p50, p90/p50) at the last decision
        self.reason = "start-up"
        self.check_every_s, self._checked_at = check_every_s, -math.inf  # how often to look for a shift
        # steady state: chunks of policy version >= steady_version, or steady_timeout_s after start
        self.steady_version, self.version, self.version_times = steady_version, -1, collections.deque(maxlen=6)
        self.steady_at = now + steady_timeout_s if steady_version > 0 else now + warmup_s
        self.earliest = now + warmup_s

    # --- measurements ---------------------------------------------------------------------------------------

    def saw_version(self, now: float, version: int) -> None:
        """Chunks acted by policy ``version`` arrive (the sim's groups; any order)."""
        if version <= self.version:
            return
        self.version = version
        self.version_times.append(now)
        if version >= self.steady_version:
            self.steady_at = min(self.steady_at, now)

    def observe(self, now: float, steps: int, step_s: Iterable[float], chunk_s: float,
                cores_used: float = math.nan) -> None:
        """An env finished its chunk at ``now``: ``steps`` steps, each costing ``step_s`` seconds (CPU), in
        ``chunk_s`` seconds from the chunk's start, keeping ``cores_used`` cores busy while it stepped."""
        self.steps.add(step_s, chunk_s, cores_used)
        if now >= self.window_start + self.settle():  # the rate: steps after the first counted chunk, over
            if self.window_first is None:            # the time since it (no bias from where a window ends)
                self.window_first = now
            else:
                self.window_steps, self.window_last = self.window_steps + steps, now

    def settle(self) -> float:
        """Seconds after a switch before steps count (chunks started in the old mode end): a chunk's p50."""
        return max(self.settle_s, self.steps.chunk())

    def update_interval(self) -> float:
        """Recent seconds between policy versions (0 before two were seen)."""
        times = list(self.version_times)
        return statistics.median(b - a for a, b in zip(times, times[1:])) if len(times) >= 3 else 0.0

    def window(self) -> float:
        """A window holds at least 8 chunks of every env after settling (slow envs: longer windows; with 4, a
        trial on 16 ms steps measured noise) and a policy update's interval (training's share of the cores
        comes and goes with the updates: each window sees a whole cycle of it)."""
        return max(self.window_s, self.settle() + 8 * self.steps.chunk(), self.settle() + self.update_interval())

    # --- decisions ----------------------------------------------------------------------------------------

    def tick(self, now: float) -> str | None:
        """Close a window that is due and act on it, or watch for a shift; returns a sentence when the mode was
        decided (a new decision, not a trial window), else None. ``self.mode`` is the mode chunks should run
        in now."""
        if not self.trial and self.decisions == 0:  # the first trial: once the run is in its steady state
            if now >= max(self.steady_at, self.earliest) and not self.steps.multi_threaded():
                self._start_trial(now, "start-up")
            return self._multi_threaded_check(now)
        if now >= self.window_start + self.window():
            span = self.window_last - self.window_first if self.window_first is not None else 0.0
            rate, mode = (self.window_steps / span if span > 0 else 0.0), self.window_mode
            self._new_window(now)
            if self.trial:
                return self._trial_window(now, mode, rate)
            if mode == self.mode:
                self.realized.append(rate)
        if self.trial or now - self._checked_at < self.check_every_s:  # the percentiles cost ~0.1 ms
            return None
        self._checked_at = now
        if decided := self._multi_threaded_check(now):
            return decided
        if not self.steps.multi_threaded() and (why := self._shifted(now)):
            self._start_trial(now, why)
        return None

    def _multi_threaded_check(self, now: float) -> str | None:
        """No trial for multi-threaded envs: rebinding is not for them; a rebinding choice becomes pinned."""
        if not self.steps.multi_threaded():
            return None
        if self.mode == REBIND or self.decisions == 0:
            self.trial, self.mode, self.decided_at, self.decisions = False, PINNED, now, self.decisions + 1
            self.window_mode = PINNED
            return f"pinned: {self.steps.multi_threaded_text()}"
        return None

    def _new_window(self, now: float) -> None:
        self.window_start, self.window_steps, self.window_first, self.window_last = now, 0, None, now

    def _start_trial(self, now: float, why: str) -> None:
        self.trial, self.pairs, self.pending, self.reason = True, [], {}, why
        self.mode = self.window_mode = PINNED
        self._new_window(now)

    def _trial_window(self, now: float, mode: int, rate: float) -> str | None:
        self.pending[mode] = rate
        if len(self.pending) < 2:  # the pair's other window next
            self.mode = self.window_mode = REBIND if mode == PINNED else PINNED
            return None
        if min(self.pending.values()) > 0:  # a window with no steps at all (everything waited) tells nothing
            self.pairs.append((self.pending[PINNED], self.pending[REBIND]))
        self.pending = {}
        ratios = [math.log(r / p) for p, r in self.pairs]
        chosen = verdict(ratios, self.min_pairs) if ratios else None
        if chosen is None and len(self.pairs) < self.max_pairs:
            # the next pair's first window: P R, R P, P R, ...: each mode as often first as second
            self.mode = self.window_mode = REBIND if len(self.pairs) % 2 else PINNED
            return None
        return self._decide(now, chosen, ratios)

    def _decide(self, now: float, chosen: int | None, ratios: list[float]) -> str:
        multi = self.steps.multi_threaded()  # seen during the trial: not for rebinding, whatever it measured
        self.trial = False
        best = chosen  # undecided after max_pairs: the point estimate's side, pinning within WORTH of a tie
        if best is None and ratios:
            best = REBIND if interval(ratios)[0] > 1.0 + WORTH else PINNED
        self.mode = self.window_mode = best if best is not None and not multi else PINNED
        pinned = statistics.median(p for p, _ in self.pairs) if self.pairs else 0.0
        rebind = statistics.median(r for _, r in self.pairs) if self.pairs else 0.0
        self.other_rate = rebind if self.mode == PINNED else pinned
        self.realized.clear()
        self.decided_at, self.decisions = now, self.decisions + 1
        self.reference = None  # taken from the next steps
        dist = self.steps.distribution()
        dist_text = f"step latency p50 {dist[0] * 1e3:.2f} ms, p90/p50 {dist[1]:.2f}" if dist else "few steps seen"
        if ratios:
            gain, low, high = interval(ratios)
            self.gain = gain
            level = f"{CONFIDENCE * 100:g} %"
            told = f"at {level}" if chosen is not None else f"not told apart at {level}: the point estimate"
            measured = (f"rebinding ran {gain:.2f}x the env steps/s of pinned whole chunks ({level} bounds "
                        f"{low:.2f}-{high:.2f}x; {told}) over {len(ratios)} pairs of {self.window():.1f} s windows "
                        f"(rebind {rebind:.0f} vs pinned {pinned:.0f} steps/s)")
        else:
            measured = "no window completed steps in both modes: pinned kept"
        return f"{NAMES[self.mode]} ({self.reason}): {measured}; {dist_text}" + (
            f"; {self.steps.multi_threaded_text()}" if multi else "")

    def _shifted(self, now: float) -> str:
        if now - self.decided_at >= self.recheck_s:
            return f"re-check after {self.recheck_s:.0f} s"
        if len(self.realized) == self.realized.maxlen and math.isfinite(self.other_rate) \
                and statistics.median(self.realized) < self.other_rate * (1 - self.drop):
            return (f"{NAMES[self.mode]} delivered {statistics.median(self.realized):.0f} env steps/s, below the "
                    f"{self.other_rate:.0f} of {NAMES[PINNED if self.mode == REBIND else REBIND]} in the last trial")
        current = self.steps.distribution()
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
        out = {"sim/core_rebinding": float(self.mode == REBIND), "sim/stepping_trial": float(self.trial),
               "sim/stepping_decisions": float(self.decisions)}
        if not math.isnan(self.gain):
            out["sim/rebinding_gain"] = self.gain
        if self.realized:
            out["sim/stepping_rate"] = self.realized[-1]
        if (dist := self.steps.distribution()) is not None:
            out["sim/step_latency_p50_ms"] = dist[0] * 1e3
            out["sim/step_latency_p90_ms"] = dist[0] * dist[1] * 1e3
        return out
