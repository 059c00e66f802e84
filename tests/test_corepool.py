"""Step-level rebinding carried out by the env workers (ebrl.resources.corepool) and its automatic choice
(ebrl.sched.stepchoice): real worker processes, a real shared-memory pool."""

from __future__ import annotations

import asyncio
import math
import os
import signal
import subprocess
import sys
import time

import numpy as np
import pytest

from ebrl.envs import EnvSpec, EnvWorker
from ebrl.resources.corepool import PINNED, REBIND, CorePool
from ebrl.sched.stepchoice import CONFIDENCE, SteppingChoice, interval, t_quantile, verdict
from ebrl.sched.stepping import RebindingStepping

CORES = sorted(os.sched_getaffinity(0))[:2]


def spec(mean_ms: float = 1.0, sigma: float = 0.0) -> EnvSpec:
    return EnvSpec("Pendulum-v1", latency="lognormal", latency_mean_ms=mean_ms, latency_sigma=sigma)


class Fleet:
    """``n`` env workers sharing one pool, stepped by RebindingStepping."""

    def __init__(self, n: int, cores: list[int], env: EnvSpec, **stepping):
        self.pool = CorePool(n, cores)
        self.workers = [EnvWorker(env, seed=e, pool=self.pool, slot=e) for e in range(n)]
        self.stepping = RebindingStepping(self.pool, **stepping)

    async def chunks(self, count: int, k: int = 4):
        await asyncio.gather(*(w.reset() for w in self.workers))
        out = []
        for _ in range(count):
            out.append(await self.stepping.run_chunk(self.workers, np.zeros((len(self.workers), k, 1), np.float32)))
        return out

    def close(self):
        for w in self.workers:
            w.close()


# --- the paper's order, under the pool's lock --------------------------------------------------------------


@pytest.fixture
def sleeper():
    """A process the pool may move between cores when it grants it one (stands in for a waiting worker)."""
    proc = subprocess.Popen(["sleep", "60"])
    yield proc.pid
    proc.kill()
    proc.wait()


def test_a_released_core_goes_to_the_never_measured_then_the_longest_waiter(sleeper):
    pool = CorePool(4, [0])
    pool.free[0] = 0  # core 0 is busy; slots 1-3 wait
    for slot, h in ((1, 0.002), (2, 0.005), (3, np.inf)):
        pool.waiting[slot], pool.H[slot], pool.pid[slot] = 1, h, sleeper
    order = []
    for _ in range(3):
        pool._give(0)
        (slot,) = [s for s in (1, 2, 3) if pool.grant[s] == 0 and s not in order]
        order.append(slot)
        assert pool.sems[slot].acquire(False)  # the grantee was woken
        pool.owner[0] = -1
    assert order == [3, 2, 1]  # never measured first, then the longest last step
    pool._give(0)
    assert pool.free[0] == 1  # nobody waits: back to the free set


def test_reclaim_hands_a_dead_workers_core_on_and_forgets_its_wait(sleeper):
    pool = CorePool(3, [0])
    pool.free[0], pool.owner[0] = 0, 0  # slot 0 holds the only core and dies
    pool.waiting[1], pool.H[1], pool.pid[1] = 1, 0.001, sleeper
    pool.waiting[2], pool.pid[2] = 1, sleeper
    pool.reclaim(2)  # a waiter that died: no longer considered
    pool.reclaim(0)
    assert pool.grant[1] == 0 and pool.owner[0] == 1 and not pool.waiting[2]


# --- real workers -------------------------------------------------------------------------------------------


def test_workers_share_the_cores_one_step_at_a_time():
    fleet = Fleet(6, CORES, spec(1.0, 0.5))
    try:
        start = time.perf_counter()
        rounds = asyncio.run(fleet.chunks(6))
        elapsed = time.perf_counter() - start
    finally:
        fleet.close()
    results = [r for done, _ in rounds for r in done]
    assert all(r.steps == 4 and len(r.step_s) == 4 and len(r.cores) == 4 for r in results)
    assert {c for r in results for c in r.cores} <= set(CORES)
    # a core runs one step at a time: the steps on it never add up to more than the time that passed
    for core in CORES:
        assert sum(s for r in results for c, s in zip(r.cores, r.step_s) if c == core) <= elapsed
    handoffs, rebinds, gap = fleet.pool.counters()
    assert handoffs > 0 and gap >= 0
    if len(CORES) > 1:
        assert rebinds > 0 and fleet.stepping.metrics()["sim/rebinds"] == rebinds


def test_a_smaller_budget_is_used_from_the_next_step():
    fleet = Fleet(4, CORES, spec(0.5))
    try:
        asyncio.run(fleet.chunks(2))
        fleet.stepping.set_budget(CORES[:1])
        after = asyncio.run(fleet.chunks(2))
    finally:
        fleet.close()
    assert {c for done, _ in after[1:] for r in done for c in r.cores} == {CORES[0]}


def test_pinned_mode_runs_whole_chunks_on_home_cores():
    fleet = Fleet(4, CORES, spec(0.5))
    fleet.pool.set_mode(PINNED)
    try:
        rounds = asyncio.run(fleet.chunks(2))
        homes = [fleet.pool.home(e) for e in range(4)]
        affinity = [os.sched_getaffinity(w.proc.pid) for w in fleet.workers]
    finally:
        fleet.close()
    assert all(r.cores == () and r.steps == 4 for done, _ in rounds for r in done)  # no core claimed
    assert affinity == [{h} for h in homes]


def test_a_worker_killed_holding_the_only_core_does_not_stall_the_others():
    fleet = Fleet(2, CORES[:1], spec(1.0))
    slow = EnvWorker(spec(3000.0), seed=9, pool=fleet.pool, slot=1)  # env 1: one step takes 3 s
    fleet.workers[1].close()
    fleet.workers[1] = slow

    async def go():
        await asyncio.gather(*(w.reset() for w in fleet.workers))
        stuck = asyncio.ensure_future(slow.chunk(np.zeros((1, 1), np.float32), timeout=0.5))
        await asyncio.sleep(0.3)  # it holds the core now
        assert fleet.pool.owner[CORES[0]] == 1
        with pytest.raises(Exception):
            await stuck  # timed out: the sim service kills and replaces it
        slow.kill()
        fleet.pool.reclaim(1)
        return await asyncio.wait_for(fleet.workers[0].chunk(np.zeros((4, 1), np.float32), timeout=10), 10)

    try:
        result = asyncio.run(go())
    finally:
        fleet.close()
    assert result.steps == 4 and set(result.cores) == {CORES[0]}


def test_a_worker_exits_when_its_parent_goes_while_it_waits_for_a_core():
    pool = CorePool(1, CORES[:1])
    pool.free[CORES[0]] = 0  # no core will ever be granted
    worker = EnvWorker(spec(0.1), seed=0, pool=pool, slot=0)
    worker.conn.send(("chunk", (np.zeros((2, 1), np.float32), True)))
    time.sleep(0.5)
    worker.conn.close()  # the sim service is gone
    worker.proc.join(10)
    assert worker.proc.exitcode == 0


# --- the automatic choice -----------------------------------------------------------------------------------


def feed(choice: SteppingChoice, now: float, rate: dict[int, float], until: float, latency: float = 0.001,
         until_trial: bool = False):
    """Chunks of 8 steps arriving every 0.05 s at the given steps/s per mode, until a decision, a new trial
    (``until_trial``) or ``until``."""
    decided = None
    while now < until and decided is None and not (until_trial and choice.trial):
        now += 0.05
        choice.observe(now, int(rate[choice.mode] * 0.05), [latency] * 8, 0.05)
        decided = choice.tick(now)
    return now, decided


@pytest.mark.parametrize("rebind_rate, expected", [(1300, REBIND), (1010, PINNED), (800, PINNED)])
def test_the_trial_keeps_rebinding_only_when_it_measures_faster(rebind_rate, expected):
    choice = SteppingChoice(now=0.0, warmup_s=0.0, steady_version=0)
    windows = []
    now, decided = 0.0, None
    while decided is None:
        windows.append(choice.mode)
        now, decided = feed(choice, now, {PINNED: 1000, REBIND: rebind_rate}, now + 0.06)
    assert choice.mode == expected and choice.decisions == 1 and not choice.trial
    assert "rebinding ran" in decided and choice.gain == pytest.approx(rebind_rate / 1000, abs=0.04)
    assert windows.count(REBIND) > 0 and windows.count(PINNED) > 0  # both measured
    assert choice.metrics()["sim/core_rebinding"] == float(expected == REBIND)


@pytest.mark.parametrize("pairs, expected", [
    ([(1000, 1060), (1010, 1075), (990, 1040)], REBIND),  # 4-6 % ahead in every pair: faster at 95 %
    ([(1000, 1030), (1000, 1031), (1000, 1029), (1000, 1030)], REBIND),  # 3 % but steady: still told apart
    ([(1000, 1060), (1040, 990), (990, 1030)], None),  # a pair the other way: cannot tell yet
    ([(1000, 700), (1000, 720)], PINNED),  # 29 % slower, within 3 %: two pairs tell
    ([(1000, 1000), (1000, 1003), (1000, 998)], PINNED),  # no gain worth the hand-offs (under 1 %)
    ([(1000, 1060)], None),  # one pair says nothing
])
def test_the_trial_verdict_is_a_confidence_rule_on_paired_windows(pairs, expected):
    ratios = [math.log(r / p) for p, r in pairs]
    assert verdict(ratios, min_pairs=2) == expected
    gain, low, high = interval(ratios)
    assert low <= gain <= high


def test_the_t_quantile_is_scipys_without_importing_scipy():
    from scipy import stats

    for dof in range(1, 201):
        assert t_quantile(dof) == pytest.approx(float(stats.t.ppf(CONFIDENCE, dof)), abs=2e-6), dof
    with pytest.raises(ValueError):
        t_quantile(0)
    out = subprocess.run([sys.executable, "-c", "import sys, ebrl.sched.fleet; print('scipy' in sys.modules)"],
                         capture_output=True, text=True, timeout=120)
    assert out.stdout.strip() == "False", out.stderr  # the simulator's process starts without it


def test_a_shifted_step_latency_starts_a_new_trial():
    choice = SteppingChoice(now=0.0, warmup_s=0.0, steady_version=0)
    now, _ = feed(choice, 0.0, {PINNED: 1000, REBIND: 1000}, 60.0)
    assert not choice.trial
    now, _ = feed(choice, now, {PINNED: 1000, REBIND: 1000}, now + 5.0)  # the reference: 1 ms steps
    now, _ = feed(choice, now, {PINNED: 1000, REBIND: 1000}, now + 5.0, latency=0.00102)  # jitter: nothing
    assert not choice.trial
    feed(choice, now, {PINNED: 1000, REBIND: 1000}, now + 30.0, latency=0.004, until_trial=True)
    assert choice.trial and "moved" in choice.reason  # the tail moves first (a mix of old and new), then p50


def test_the_choice_is_rechecked_after_a_while():
    choice = SteppingChoice(now=0.0, warmup_s=0.0, recheck_s=20.0, steady_version=0)
    now, _ = feed(choice, 0.0, {PINNED: 1000, REBIND: 1000}, 60.0)
    end, _ = feed(choice, now, {PINNED: 1000, REBIND: 1000}, now + 60.0, until_trial=True)
    assert choice.trial and "re-check" in choice.reason and 20.0 <= end - now <= 21.1  # at the next look (1 s)


class Workload:
    """A run's sim as the choice sees it, on a fake clock: chunks of 8 steps every 0.05 s at env steps/s that
    depend on the mode and the phase (``phases``: (from second, {mode: steps/s}, step latency)), with 3 %
    noise per chunk, and a new policy version every second from ``versions_from`` on."""

    def __init__(self, choice: SteppingChoice, phases, versions_from: float = 0.0, seed: int = 0,
                 sigma: float = 0.3):
        self.choice, self.phases, self.versions_from, self.sigma = choice, phases, versions_from, sigma
        self.rng, self.now, self.modes = np.random.default_rng(seed), 0.0, []  # (time, mode) of each decision

    def run(self, until: float) -> list[str]:
        decisions = []
        while self.now < until:
            self.now += 0.05
            if self.now >= self.versions_from:
                self.choice.saw_version(self.now, int(self.now - self.versions_from))
            _, rates, latency = [p for p in self.phases if p[0] <= self.now][-1]
            steps = rates[self.choice.mode] * 0.05 * self.rng.normal(1.0, 0.03)
            self.choice.observe(self.now, int(round(steps)), list(self.rng.lognormal(np.log(latency), self.sigma, 8)), 0.05)
            if (decided := self.choice.tick(self.now)) is not None:
                decisions.append(decided)
                self.modes.append((self.now, self.choice.mode))
        return decisions


def test_the_first_trial_waits_for_training_steady_state():
    """No trial in the start-up's transients: the first runs once chunks of policy version 2 arrive."""
    choice = SteppingChoice(now=0.0)
    load = Workload(choice, [(0.0, {PINNED: 1000, REBIND: 1300}, 0.001)], versions_from=20.0)
    load.run(21.5)  # version 0 at 20 s, version 2 at 22 s
    assert not choice.trial and choice.decisions == 0 and choice.mode == PINNED
    load.run(23.0)
    assert choice.trial
    decided = load.run(90.0)
    assert choice.mode == REBIND and "(start-up)" in decided[0] and "at 95 %" in decided[0]
    assert "1.30x" in decided[0] or "1.29x" in decided[0] or "1.31x" in decided[0], decided[0]
    # with no version ever reaching 2 (a run of one iteration), the trial starts after steady_timeout_s
    late = SteppingChoice(now=0.0, steady_timeout_s=30.0)
    Workload(late, [(0.0, {PINNED: 1000, REBIND: 1300}, 0.001)], versions_from=1e9).run(29.0)
    assert not late.trial and late.decisions == 0


@pytest.mark.parametrize("p50_ms, sigma", [(4.0, 1.0), (4.0, 0.1), (0.5, 1.0)])
def test_until_the_first_trial_the_envs_run_pinned_whatever_their_step_latencies(p50_ms, sigma):
    """No model decides before the trial measures: long heavy-tailed steps (where rebinding might pay), W1-like
    steps (robosuite Lift: 3.9 ms, p90/p50 1.15) and short ones all start pinned; the trial then decides on
    rates alone (here rebinding delivers more whatever the latencies)."""
    choice = SteppingChoice(now=0.0)
    load = Workload(choice, [(0.0, {PINNED: 1000, REBIND: 1300}, p50_ms / 1e3)], versions_from=20.0, sigma=sigma)
    load.run(21.5)  # 21.5 s, 3400 chunks, policy versions 0 and 1: no trial yet
    assert choice.mode == PINNED and choice.decisions == 0 and not choice.trial
    decided = load.run(90.0)
    assert choice.mode == REBIND and decided and "(start-up)" in decided[0]


def test_the_choice_follows_a_workload_whose_better_stepping_changes_mid_run():
    """A step cost that changes after some seconds (issue 36): 1 ms steps on which pinning delivers more, then
    heavy-tailed 3 ms steps on which rebinding does (the latencies moved: a new trial), then, with the same
    latencies, rebinding's rate falls under what pinning delivered (what the run delivers: a new trial)."""
    choice = SteppingChoice(now=0.0, warmup_s=0.0, steady_version=0)
    load = Workload(choice, [(0.0, {PINNED: 1000, REBIND: 850}, 0.001),
                             (120.0, {PINNED: 600, REBIND: 800}, 0.003),
                             (240.0, {PINNED: 600, REBIND: 450}, 0.003)])
    decisions = load.run(360.0)
    # (a change of latencies is seen twice when it comes: the tail moves first, old and new steps mixed, then p50)
    changes = [(t, mode) for i, (t, mode) in enumerate(load.modes) if i == 0 or mode != load.modes[i - 1][1]]
    assert [mode for _, mode in changes] == [PINNED, REBIND, PINNED], decisions
    (t1, _), (t2, _), (t3, _) = changes
    assert t1 < 60 and 120 < t2 < 180 and 240 < t3 < 300, load.modes  # each within a minute of the change
    assert "step latency" in decisions[1] and "moved" in decisions[1]
    assert "delivered" in decisions[-1] and "below" in decisions[-1]
    assert choice.metrics()["sim/stepping_decisions"] == len(decisions) <= 4


def test_a_trial_that_cannot_tell_at_its_last_pair_takes_the_point_estimate():
    """Windows as a noisy machine measures them (rebinding ahead by 25 %, behind by 17 %, ahead by 20 %): the
    last pair (max_pairs = 3 here) cannot tell them apart at 95 %, and the run takes the better estimate
    (rebinding 1.08x) rather than the tie's side."""
    choice = SteppingChoice(now=0.0, warmup_s=0.0, steady_version=0, max_pairs=3)
    load = Workload(choice, [(0.0, {PINNED: 1000, REBIND: 1100}, 0.001)])
    steps = {PINNED: iter([1000, 1200, 900]), REBIND: iter([1250, 1000, 1080])}  # each window's rate
    rates = load.phases[0][1]
    decided = []
    while not decided and load.now < 60.0:  # one rate per window: what a noisy machine measures
        window, mode = choice.window_start, choice.mode
        rates[mode] = next(steps[mode], rates[mode])
        while choice.window_start == window and not decided:
            decided = load.run(load.now + 0.05)
    assert choice.mode == REBIND and "not told apart at 95 %: the point estimate" in decided[0], decided


def test_no_difference_keeps_pinning():
    choice = SteppingChoice(now=0.0, warmup_s=0.0, steady_version=0)
    decided = Workload(choice, [(0.0, {PINNED: 1000, REBIND: 1000}, 0.001)]).run(120.0)
    assert choice.mode == PINNED and "(start-up): rebinding ran 1.00x" in decided[0], decided


def test_auto_switches_the_pool_and_reports_periods_and_the_decision():
    decisions, periods = [], []
    choice = SteppingChoice(now=time.monotonic(), warmup_s=0.0, window_s=0.2, settle_s=0.02, steady_version=0)
    fleet = Fleet(4, CORES, spec(0.2), choice=choice, on_decision=decisions.append,
                  on_mode=lambda mode, a, b: periods.append(mode))

    async def until_decided():
        await asyncio.gather(*(w.reset() for w in fleet.workers))
        seen = set()
        for _ in range(2000):
            await fleet.stepping.run_chunk(fleet.workers, np.zeros((4, 4, 1), np.float32))
            seen.add(fleet.pool.mode)
            if decisions:
                return seen
        raise AssertionError("no decision")

    try:
        seen = asyncio.run(until_decided())
    finally:
        fleet.close()
    assert seen == {PINNED, REBIND}  # the trial ran both
    assert fleet.pool.mode == choice.mode and set(periods) == {PINNED, REBIND}
    assert "rebinding ran" in decisions[0]
    assert {"sim/core_rebinding", "sim/rebinding_gain", "sim/core_handoffs"} <= set(fleet.stepping.metrics())


def test_a_worker_that_dies_holding_the_only_core_is_reclaimed_within_the_chunk():
    pool = CorePool(3, CORES[:1])
    workers = [EnvWorker(spec(3000.0 if e == 0 else 1.0), seed=e, pool=pool, slot=e) for e in range(3)]
    stepping = RebindingStepping(pool)
    stepping.timeout = 60.0  # far longer than the test: the others must not wait for it

    async def go():
        await asyncio.gather(*(w.reset() for w in workers))
        chunk = asyncio.ensure_future(stepping.run_chunk(workers, np.zeros((3, 3, 1), np.float32)))
        for _ in range(100):  # env 0 never measured goes first, and takes the only core for 3 s
            await asyncio.sleep(0.05)
            if pool.owner[CORES[0]] == 0:
                break
        os.kill(workers[0].proc.pid, signal.SIGKILL)
        return await asyncio.wait_for(chunk, 30)

    try:
        started = time.monotonic()
        results, _ = asyncio.run(go())
        took = time.monotonic() - started
    finally:
        for w in workers:
            w.close()
    assert isinstance(results[0], Exception) and "died" in str(results[0])
    assert [r.steps for r in results[1:]] == [3, 3] and took < 30
