"""The supervisor with small Python scripts as its children: restart policy, requota, shutdown in order."""

from __future__ import annotations

import asyncio
import os
import signal
import sys
import time

import psutil
import pytest

from ebrl import procenv
from ebrl.supervisor import RestartPolicy, Supervisor

CRASH = "import sys; print('up', flush=True); sys.exit(3)"
SHOW_ENV = ("import os, sys, time; print('env', *(os.environ.get(k, '-') for k in sys.argv[1:]), flush=True); "
            "time.sleep(600)")
STUBBORN = ("import signal, subprocess, sys, time; signal.signal(signal.SIGTERM, signal.SIG_IGN); "
            "grandchild = subprocess.Popen([sys.executable, '-c', 'import time; time.sleep(600)']); "
            "print('ready', grandchild.pid, flush=True); time.sleep(600)")
SLEEPER = "import time; print('ready', flush=True); time.sleep(600)"
LEAKY = ("import subprocess, sys; grandchild = subprocess.Popen(['sleep', '600']); "  # left in its process group
         "print('grandchild', grandchild.pid, flush=True); sys.exit(3)")


class Recorded:
    """What the supervisor said and recorded as events."""

    def __init__(self):
        self.lines: list[str] = []
        self.events: list[tuple[str, str]] = []

    def say(self, text: str) -> None:
        self.lines.append(text)

    def event(self, kind: str, text: str) -> None:
        self.events.append((kind, text))


@pytest.fixture
def made(tmp_path):
    """make(scripts, ...) -> (Supervisor, Recorded): ``scripts`` maps a role to the Python code its children run
    (with extra arguments: the rest of the tuple); every child is killed at the end."""
    made = []

    def make(scripts: dict[str, tuple[str, ...]], policy=RestartPolicy(True, 2, first_delay_s=0.01), **kw):
        said = Recorded()
        sup = Supervisor(lambda role, instance: [sys.executable, "-c", *scripts[role]], tmp_path, policy,
                         say=said.say, event=said.event, **kw)
        made.append(sup)
        return sup, said

    yield make
    for sup in made:
        for child in sup.children:
            if child.proc.poll() is None:
                os.killpg(child.proc.pid, signal.SIGKILL)
                child.proc.wait(5)


def until(condition, what: str, timeout: float = 60.0) -> None:
    deadline = time.monotonic() + timeout
    while not condition():
        assert time.monotonic() < deadline, f"not within {timeout:.0f} s: {what}"
        time.sleep(0.02)


def running(sup: Supervisor, condition) -> bool:
    """One supervision step, which must find no failure; then ``condition()``."""
    failure = sup.check()
    assert failure is None, failure
    return condition()


def gone(pid: int) -> bool:
    try:
        return psutil.Process(pid).status() == psutil.STATUS_ZOMBIE  # killed, waiting for an adoptive parent
    except psutil.NoSuchProcess:
        return True


def first_failure(sup: Supervisor, timeout: float = 60.0) -> str:
    deadline = time.monotonic() + timeout
    while (failure := sup.check()) is None:
        assert time.monotonic() < deadline, f"no failure within {timeout:.0f} s"
        time.sleep(0.02)
    return failure


def test_a_crashing_child_is_restarted_up_to_the_limit_then_reported(made):
    sup, said = made({"crash": (CRASH,)})
    child = sup.start("crash", 0)
    assert first_failure(sup) == "crash/0 exited with status 3 (after 2 restarts)"
    assert child.restarts == 2 and sup.restarts() == {"crash/0": 2}
    assert sup.metrics() == {"launcher/restarts": 2.0, "launcher/restarts_crash": 2.0, "launcher/requotas": 0.0}
    assert [kind for kind, _ in said.events] == ["exited", "restart", "exited", "restart", "exited"]
    assert sum("restarting it in" in line for line in said.lines) == 2
    log = child.log_path.read_text()
    assert log.count("up") == 3 and "--- restart 2 by the launcher ---" in log


def test_an_optional_child_is_restarted_then_given_up_and_the_run_goes_on(made):
    """The tracking sinks (``log``) are optional: a log service that keeps dying is restarted like any child, then
    left dead; the supervisor never reports it as the run's failure, and the other children keep running."""
    sup, said = made({"log": (CRASH,), "sim": (SLEEPER,)}, optional=("log",))
    log_child, sim_child = sup.start("log", 0), sup.start("sim", 0)
    until(lambda: running(sup, lambda: log_child.given_up), "the log service given up")
    assert log_child.restarts == 2 and sim_child.proc.poll() is None
    assert said.events[-1] == ("exited", "log/0 exited with status 3 (after 2 restarts); the run goes on without it")
    for _ in range(20):  # given up for good: no failure, no further restart
        assert sup.check() is None
        time.sleep(0.01)
    assert log_child.restarts == 2 and log_child.log_path.read_text().count("up") == 3
    sup_never, said_never = made({"log": (CRASH,)}, policy=RestartPolicy(False, 5), optional=("log",))
    child = sup_never.start("log", 0)
    until(lambda: running(sup_never, lambda: child.given_up), "given up at its first exit (run.restart = never)")
    assert "the run goes on without it" in said_never.lines[-1]


def test_without_a_restart_policy_the_first_exit_is_the_failure(made):
    sup, said = made({"crash": (CRASH,)}, policy=RestartPolicy(False, 5))
    sup.start("crash", 0)
    assert first_failure(sup) == "crash/0 exited with status 3" and sup.restarts() == {}
    assert "last lines of" in said.lines[-1] and "up" in said.lines[-1]  # the child's log tail is shown


def test_restart_delays_double_up_to_a_cap():
    policy = RestartPolicy(True, 3)
    assert [policy.delay(n) for n in (0, 1, 2, 10)] == [1.0, 2.0, 4.0, 30.0]
    assert policy.allows(2) and not policy.allows(3) and not RestartPolicy(False, 3).allows(0)


def test_a_new_gpu_share_restarts_the_stage_with_it_and_is_no_failure_restart(made):
    share = "CUDA_MPS_ACTIVE_THREAD_PERCENTAGE"
    sup, said = made({"gen": (SHOW_ENV, share)}, gpu_env={"gen": {share: "50"}})
    child = sup.start("gen", 0)
    until(lambda: "env 50" in child.log_path.read_text(), "gen started with its first share")
    asked = sup.new_gpu_share("gen", {share: "30"}, version=2)
    assert asked == [child] and child.requota
    assert sup.new_gpu_share("gen", {share: "20"}, version=2) == []  # a version already applied
    child.proc.terminate()  # it stops at its safe point (asked over the bus by the launcher)
    until(lambda: running(sup, lambda: "env 30" in child.log_path.read_text()), "gen back with the new share")
    assert child.restarts == 0 and sup.restarts() == {} and not child.requota
    assert said.events == [("requota", f"gen/0 started again with GPU share {{'{share}': '30'}}")]
    assert sup.new_gpu_share("gen", {share: "30"}, version=3) == []  # the share it has: nothing to do
    assert sup.new_gpu_share("train", {share: "30"}, version=3) == []  # no such stage on this host


def test_a_failed_training_rank_restarts_the_group_with_a_new_rendezvous_past_every_version(made):
    sup, said = made({"train": (SHOW_ENV, procenv.DIST_ADDR, procenv.VERSION_FLOOR)}, train_ranks=2,
                     version_floor=lambda: 7)
    ranks = [sup.start("train", 0), sup.start("train", 1)]
    first = sup.dist_addr
    until(lambda: all(f"env {first} -" in r.log_path.read_text() for r in ranks), "both ranks up")
    ranks[0].proc.kill()
    until(lambda: running(sup, lambda: all(f"env {sup.dist_addr} 7" in r.log_path.read_text() for r in ranks)),
          "both ranks started again")
    assert sup.dist_addr != first and sup.restarts() == {"train/0": 1, "train/1": 1}


def test_shutdown_asks_then_terminates_then_kills_the_process_group_of_a_child_ignoring_sigterm(made):
    sup, said = made({"stubborn": (STUBBORN,), "polite": (SLEEPER,)})
    stubborn, polite = sup.start("stubborn", 0), sup.start("polite", 0)
    until(lambda: all("ready" in c.log_path.read_text() for c in (stubborn, polite)), "both children ready")
    grandchild = int(stubborn.log_path.read_text().split()[-1])
    asked: list[str] = []

    async def ask_to_stop(child) -> None:
        asked.append(child.name)

    asyncio.run(sup.shutdown(ask_to_stop, stop_grace_s=0.2, shutdown_s=1.0))
    assert asked == ["stubborn/0", "polite/0"]
    assert polite.proc.returncode == -signal.SIGTERM
    assert stubborn.proc.returncode == -signal.SIGKILL
    assert "ebrl: stubborn/0 ignored SIGTERM; killing it" in said.lines
    until(lambda: gone(grandchild), "the stubborn child's own child killed with its process group")


def test_a_child_that_exited_has_its_process_group_killed_before_it_starts_again(made):
    """A child that leaves a grandchild in its process group and exits: the grandchild is killed as soon as the
    exit is noticed (before the restart, and when the child fails for good), so no orphan outlives it."""
    sup, said = made({"leaky": (LEAKY,)}, policy=RestartPolicy(True, 1, first_delay_s=600.0))
    child = sup.start("leaky", 0)

    def grandchildren() -> list[int]:
        return [int(line.split()[1]) for line in child.log_path.read_text().splitlines()
                if line.startswith("grandchild")]

    until(lambda: running(sup, lambda: child.restart_at is not None), "its exit noticed, its restart scheduled")
    until(lambda: gone(grandchildren()[0]), "its grandchild killed before the restart", timeout=10)
    sup.restart(child)  # now, not in 600 s
    assert first_failure(sup) == "leaky/0 exited with status 3 (after 1 restarts)"
    assert len(grandchildren()) == 2
    until(lambda: gone(grandchildren()[1]), "the last child's grandchild killed too", timeout=10)
