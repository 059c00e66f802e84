"""Greedy core rebinding, driven by a fake clock (a discrete-event loop over known step latencies)."""

import heapq

import pytest

from ebrl.sched.rebind import CoreRebinding


def simulate(sched, latency, K, envs, until_chunks=1, on_time=None):
    """Run chunks of K steps for ``envs`` to completion; return the dispatch log [(t, env, core)]."""
    t, events, log = 0.0, [], []
    done_chunks = {e: 0 for e in envs}
    for e in envs:
        sched.add_env(e)
        sched.submit_chunk(e, K)

    def pump():
        for env, core in sched.dispatch():
            assert list(sched.running).count(env) == 1
            log.append((t, env, core))
            heapq.heappush(events, (t + latency(env), env, core))

    pump()
    while events:
        t, env, core = heapq.heappop(events)
        if on_time:
            on_time(t, sched)
        if sched.complete(env, latency(env)):
            done_chunks[env] += 1
            if done_chunks[env] < until_chunks:
                sched.submit_chunk(env, K)
        pump()
    return log, t


def test_never_measured_first_then_longest_latency_first():
    sched = CoreRebinding([0])
    lat = {0: 1.0, 1: 3.0, 2: 2.0}
    log, _ = simulate(sched, lat.get, K=2, envs=[0, 1, 2])
    order = [env for _, env, _ in log]
    assert order[:3] == [0, 1, 2]  # no history yet: every env is tried once (ties keep insertion order)
    assert order[3:] == [1, 2, 0]  # then the slowest ready env first


def test_no_duplicate_dispatch_and_every_step_runs_once():
    sched = CoreRebinding([0, 1, 2])
    lat = {e: 0.5 + 0.1 * e for e in range(5)}
    log, _ = simulate(sched, lat.get, K=4, envs=range(5), until_chunks=3)
    per_env = {e: sum(1 for _, env, _ in log if env == e) for e in range(5)}
    assert per_env == {e: 12 for e in range(5)}
    # an env is never on two cores at once: its dispatches are at least one latency apart
    for e in range(5):
        times = [t for t, env, _ in log if env == e]
        assert all(b - a >= lat[e] - 1e-9 for a, b in zip(times, times[1:]))


def test_cores_stay_idle_when_nothing_is_ready():
    sched = CoreRebinding([0, 1, 2, 3])
    sched.add_env(0)
    sched.add_env(1)
    assert sched.dispatch() == []  # no env has actions
    sched.submit_chunk(0, 3)
    assert sched.dispatch() == [(0, 0)]  # one ready env, one core; the others stay idle
    assert sched.dispatch() == []
    assert sched.idle_cores == 3
    assert not sched.complete(0, 0.1)
    with pytest.raises(RuntimeError):
        sched.submit_chunk(0, 3)  # chunk not finished yet


def test_episode_end_drops_the_rest_of_the_chunk():
    sched = CoreRebinding([0])
    sched.add_env(0)
    sched.submit_chunk(0, 8)
    sched.dispatch()
    assert sched.complete(0, 0.1, chunk_ended=True)
    assert sched.ready() == []


def test_budget_change_mid_run():
    sched = CoreRebinding([0, 1])
    lat = {e: 1.0 for e in range(4)}
    cores_over_time = []

    def shrink_then_grow(t, s):
        if 2.0 <= t < 2.5 and s.budget == [0, 1]:
            s.set_budget([1])
        if t >= 6.0 and s.budget == [1]:
            s.set_budget([1, 2, 3])
        cores_over_time.append((t, set(s.running.values())))

    log, end = simulate(sched, lat.get, K=3, envs=range(4), until_chunks=1, on_time=shrink_then_grow)
    assert len(log) == 12
    used_after_shrink = {core for t, _, core in log if 2.0 < t < 6.0}
    assert used_after_shrink == {1}  # core 0 left the budget and was never dispatched again
    after_growth = {core for t, _, core in log if t >= 6.0}
    assert after_growth <= {1, 2, 3} and len(after_growth) >= 2  # a new core was used at once
    with pytest.raises(ValueError):
        sched.set_budget([])
