"""Env worker hygiene with real processes: workers die with their sim service (even in the middle of a step),
and an env whose worker fails at every step is given up after a bounded number of replacements while the other
envs keep running."""

from __future__ import annotations

import asyncio
import os
import signal
import subprocess
import sys
import textwrap
import time
from pathlib import Path

import numpy as np
import psutil

from ebrl.envs import EnvSpec
from ebrl.envs.worker import WorkerFailed
from ebrl.sched.fleet import MAX_REPLACEMENTS, EnvFleet
from ebrl.sched.modes import Schedule
from helpers import ROOT

TESTS = Path(__file__).resolve().parent
ENV = dict(os.environ, PYTHONPATH=os.pathsep.join([str(ROOT), str(TESTS), os.environ.get("PYTHONPATH", "")]))


def gone(pid: int) -> bool:
    try:
        return psutil.Process(pid).status() == psutil.STATUS_ZOMBIE  # dead, waiting for an adoptive parent
    except psutil.NoSuchProcess:
        return True


def until(condition, what: str, timeout: float = 60.0) -> None:
    deadline = time.monotonic() + timeout
    while not condition():
        assert time.monotonic() < deadline, f"not within {timeout:.0f} s: {what}"
        time.sleep(0.05)


# A sim service's part in this: two env workers, env 0 in the middle of a step that lasts ten minutes.
FAKE_SIM = textwrap.dedent("""
    import asyncio, sys, time
    import numpy as np
    from ebrl.envs import EnvSpec, EnvWorker
    spec = EnvSpec("faulty_envs:Faulty-v0", kwargs={"fault": "sleep", "bad_env": 0, "marker": sys.argv[1]})
    workers = [EnvWorker(spec, seed=env) for env in range(2)]

    async def reset():
        await asyncio.gather(*(w.reset() for w in workers))

    asyncio.run(reset())
    workers[0].conn.send(("chunk", (np.zeros((2, 1), np.float32), True)))  # env 0: a step of ten minutes
    print(*(w.proc.pid for w in workers), flush=True)
    time.sleep(600)
""")


def test_env_workers_die_with_their_sim_service_even_in_the_middle_of_a_step(tmp_path):
    marker = tmp_path / "stepping"
    sim = subprocess.Popen([sys.executable, "-c", FAKE_SIM, str(marker)], cwd=ROOT, env=ENV, stdout=subprocess.PIPE,
                           text=True)
    try:
        workers = [int(pid) for pid in sim.stdout.readline().split()]
        assert len(workers) == 2, f"the fake sim service failed ({sim.wait()})"
        until(marker.exists, "env 0 inside its step")
        forkserver = [p.pid for p in psutil.Process(sim.pid).children() if p.pid not in workers]
        sim.send_signal(signal.SIGKILL)  # no chance to close anything
        until(lambda: all(gone(pid) for pid in workers + forkserver), "the env workers gone with the sim service",
              timeout=30)
    finally:
        sim.kill()
        sim.wait()
        sim.stdout.close()


# A process that forks a child, then exits at once: the child asks for the parent-death signal only after its
# parent is gone, so the signal would never come; die_with_parent says so.
ORPHAN = textwrap.dedent("""
    import os, time
    from ebrl.envs.worker import die_with_parent
    parent = os.getpid()
    if os.fork() == 0:
        while os.getppid() == parent:
            time.sleep(0.01)
        print("orphan", die_with_parent(parent), flush=True)
        os._exit(0)
    print("child", die_with_parent(os.getppid()), flush=True)
""")


def test_a_worker_whose_parent_died_before_it_asked_for_the_signal_knows_it():
    out = subprocess.run([sys.executable, "-c", ORPHAN], cwd=ROOT, env=ENV, capture_output=True, text=True,
                         timeout=60).stdout  # returns when both closed the pipe
    assert sorted(out.split("\n")[:2]) == ["child True", "orphan False"], out


# --- env workers given up ----------------------------------------------------------------------------------


def fleet(fault: str, bad_env: int, share: int = 1) -> EnvFleet:
    spec = EnvSpec("faulty_envs:Faulty-v0", kwargs={"fault": fault, "bad_env": bad_env})
    schedule = Schedule(mode="ebrl", groups=2, envs_per_group=2, stepping="async", core_rebinding=False,
                        overlap=True, max_staleness=1, rollout_length=8, sim_cores=sorted(os.sched_getaffinity(0))[:1],
                        gen_cores=[], train_cores=[])
    return EnvFleet(spec, schedule, host=0, seed=0, share=share)


async def drive(envs: EnvFleet, chunks: int, between=None) -> dict[int, int]:
    """A group loop's part, for every group: ``chunks`` chunks on every env not given up, a failed worker
    recovered (``between(envs)`` after each round); how many chunks each env answered."""
    for g in envs.groups:
        await envs.reset_group(g)
    answered = {int(env): 0 for g in envs.groups for env in envs.env_ids(g)}
    for _ in range(chunks):
        for g in envs.groups:
            active = [i for i, env in enumerate(envs.env_ids(g)) if not envs.given_up_env(int(env))]
            if not active:
                continue
            done, _ = await envs.run_chunk(g, active, np.zeros((len(active), 2, 1), np.float32))
            for i, result in zip(active, done):
                env = int(envs.env_ids(g)[i])
                if isinstance(result, WorkerFailed):
                    envs.episodes.set(env, envs.episodes.index[env] + 1)
                    await envs.recover(g, i, envs.episodes.index[env])
                else:
                    answered[env] += 1
        if between is not None:
            between(envs)
    return answered


def test_an_env_failing_at_every_step_is_given_up_after_bounded_replacements_and_the_others_go_on(caplog):
    envs = fleet("raise", bad_env=1)
    try:
        answered = asyncio.run(drive(envs, chunks=MAX_REPLACEMENTS + 4))
        assert envs.given_up == 1 and envs.given_up_env(1) and envs.failures[1] == MAX_REPLACEMENTS + 1
        assert answered == {0: MAX_REPLACEMENTS + 4, 1: 0, 2: MAX_REPLACEMENTS + 4, 3: MAX_REPLACEMENTS + 4}
        assert envs.count() == 3 and not envs.workers[0][1].proc.is_alive()
        assert asyncio.run(envs.recover(0, 1, episode=99)) is None  # given up for good
        assert (f"env 1 given up: its worker failed {MAX_REPLACEMENTS + 1} times in a row without answering a "
                f"chunk (after {MAX_REPLACEMENTS} replacements)") in caplog.text
    finally:
        envs.close()


def test_a_replacement_that_fails_at_once_is_replaced_again_until_the_env_is_given_up():
    envs = fleet("raise-always", bad_env=2)  # its first worker fails at a step, every later one at its reset
    try:
        answered = asyncio.run(drive(envs, chunks=3))
        assert envs.given_up_envs == {2} and answered == {0: 3, 1: 3, 2: 0, 3: 3}
    finally:
        envs.close()


def test_a_worker_that_answers_between_its_failures_is_never_given_up():
    envs = fleet("", bad_env=-1)

    def kill_env_0(envs: EnvFleet) -> None:  # once its worker answered a chunk, it dies
        if envs.workers[0][0].chunks_done:
            envs.workers[0][0].proc.kill()

    try:
        rounds = MAX_REPLACEMENTS + 3
        answered = asyncio.run(drive(envs, chunks=2 * rounds, between=kill_env_0))
        assert envs.given_up == 0 and envs.count() == 4
        assert answered[0] == rounds and answered[1] == 2 * rounds  # every other chunk: replaced after each kill
        assert envs.failures[0] == 1  # each failure the first since a chunk was answered
    finally:
        envs.close()


def test_grpo_group_mates_are_given_up_together():
    envs = fleet("raise", bad_env=2, share=2)  # envs 2 and 3 start from the same states (seed 2): both fail
    try:
        answered = asyncio.run(drive(envs, chunks=MAX_REPLACEMENTS + 3))
        assert envs.given_up_envs == {2, 3} and envs.given_up == 2 and envs.count() == 2
        assert answered[0] == answered[1] == MAX_REPLACEMENTS + 3
        assert not any(w.proc.is_alive() for w in envs.workers[1])
    finally:
        envs.close()
