"""Fault injection into real `ebrl up` runs on loopback: each fault is survived, versions stay monotonic,
and the run finishes its iterations.

Faults: kill -9 an env worker mid-run; hang one (SIGSTOP); kill -9 gen; kill -9 train (it resumes from its
checkpoint); flood data keys with random bytes. And `ebrl up --resume RUN_DIR` continues a stopped run.
"""

import json
import signal
import subprocess
import sys

import msgpack
import psutil
import pytest

from ebrl import keys
from ebrl.testing import Run, StatsWatcher
from helpers import OWN_PROCESSES, ROOT, up

QUICK = ("run.iterations=8", "train.batch_size=256", "train.checkpoint_every=1")
FINISH_S = 300  # generous: a loaded machine runs 8 iterations slowly


def quick(out_dir, name: str, *overrides: str) -> Run:
    """The quickstart for 8 iterations, checkpointing after each."""
    return up(out_dir, "configs/quickstart.toml", *QUICK, *overrides, name=name)


def wait_version(stats: StatsWatcher, version: int, timeout: float = 300) -> None:
    stats.wait_for(lambda: (stats.latest("train/0", "train/policy_version") or 0) >= version, timeout,
                   f"policy v{version}")


def service(run: Run, role: str) -> psutil.Process:
    """The process that runs ``role``/0: its own (``python -m ebrl.services.<role>``) or one it shares
    (``python -m ebrl.process --service <role>/0 ...``; on this CPU host "auto" puts sim and gen in one)."""
    for child in psutil.Process(run.proc.pid).children():
        argv = child.cmdline()
        if f"ebrl.services.{role}" in argv or f"{role}/0" in argv:
            return child
    raise AssertionError(f"no {role} service running")


def env_workers(run: Run) -> list[psutil.Process]:
    forkservers = [p for p in service(run, "sim").children() if "forkserver" in " ".join(p.cmdline())]
    return [w for f in forkservers for w in f.children()]


def monotonic(values) -> bool:
    return all(b >= a for a, b in zip(values, values[1:]))


def check_survived(stats: StatsWatcher, code: int) -> None:
    """The run finished its iterations; versions never went back; nothing malformed or acted by an unknown
    version reached training."""
    assert code == 0, stats.run.output
    assert stats.latest("train/0", "train/policy_version") == 8
    assert monotonic(stats.values("train/0", "train/policy_version"))
    assert stats.latest("train/0", "train/future_version_dropped", 0) == 0


def test_a_killed_env_worker_is_replaced_and_the_others_keep_running(tmp_path):
    with quick(tmp_path, "kill-worker") as run, StatsWatcher(run) as stats:
        wait_version(stats, 2)
        workers = env_workers(run)
        assert len(workers) == 8
        workers[3].send_signal(signal.SIGKILL)
        code = run.wait(FINISH_S)
    check_survived(stats, code)
    assert stats.latest("sim/0", "sim/worker_restarts") == 1
    assert monotonic(stats.values("gen/0", "gen/policy_version"))
    assert stats.latest("train/0", "bus/malformed", 0) == 0  # nothing half-built reached training


@pytest.mark.slow
def test_a_hung_env_worker_is_killed_after_the_step_timeout(tmp_path):
    # 5 s: long enough that no step of a healthy worker on a loaded machine takes it, so only the hung one restarts
    with quick(tmp_path, "hang-worker", "sim.step_timeout=5.0") as run, StatsWatcher(run) as stats:
        wait_version(stats, 2)
        hung = env_workers(run)[5]
        hung.send_signal(signal.SIGSTOP)
        code = run.wait(FINISH_S)
    check_survived(stats, code)
    assert stats.latest("sim/0", "sim/worker_restarts") == 1
    assert not hung.is_running() or hung.status() == psutil.STATUS_ZOMBIE  # killed, not left stopped


@pytest.mark.slow  # the fast suite's 10 minutes; a killed process restarted, in the fast suite: tests/test_shared_process.py
def test_a_killed_gen_is_restarted_and_every_group_is_served_again(tmp_path):
    # train.max_pending = one batch: training cannot have the rest of the run's data buffered when gen dies (with
    # the default 8192 it could finish every iteration before the restart, and there was nothing to restart for)
    # gen in a process of its own (a shared one restarting whole: tests/test_shared_process.py)
    with quick(tmp_path, "kill-gen", "train.max_pending=256", OWN_PROCESSES) as run, StatsWatcher(run) as stats:
        wait_version(stats, 2)
        service(run, "gen").send_signal(signal.SIGKILL)
        code = run.wait(FINISH_S)
    check_survived(stats, code)
    assert "gen/0 exited with status -9; restarting it" in run.output
    assert stats.latest("launcher/0", "launcher/restarts_gen") == 1
    summary = json.loads((run.run_dir / "summary.json").read_text())
    assert summary["restarts"] == {"gen/0": 1}


@pytest.mark.slow
def test_a_killed_train_resumes_from_its_checkpoint_with_versions_never_reused(tmp_path):
    with quick(tmp_path, "kill-train") as run, StatsWatcher(run) as stats:
        wait_version(stats, 3)
        service(run, "train").send_signal(signal.SIGKILL)
        code = run.wait(FINISH_S)
    check_survived(stats, code)
    assert "train/0 exited with status -9; restarting it" in run.output
    assert monotonic(stats.values("gen/0", "gen/policy_version"))  # gen never went back to an older version
    log = (run.run_dir / "logs" / "train-0.log").read_text()
    assert "resumed from" in log and "checkpoints/v" in log


@pytest.mark.slow
def test_a_train_killed_in_its_first_update_without_overlap_does_not_stall_the_run(tmp_path):
    # colocated: no overlap, so generation waits for v1 before iteration 1; the killed train took iteration 0's
    # data with it. Slow steps (~5 ms) make iteration 0 last seconds, so the kill lands inside it.
    with quick(tmp_path, "kill-first-train", "run.mode=colocated", "env.latency=lognormal",
               "env.latency_mean_ms=5", "run.iterations=3") as run, StatsWatcher(run) as stats:
        stats.wait_for(lambda: (stats.latest("sim/0", "sim/env_steps") or 0) > 0, 120, "the first env steps")
        assert (stats.latest("train/0", "train/policy_version") or 0) == 0
        service(run, "train").send_signal(signal.SIGKILL)
        code = run.wait(FINISH_S)
    assert code == 0, run.output
    assert stats.latest("train/0", "train/policy_version") >= 3
    assert monotonic(stats.values("train/0", "train/policy_version"))
    log = (run.run_dir / "logs" / "train-0.log").read_text()
    assert "versions up to v0 were published before the restart; the initial weights continue as v1" in log


def test_random_bytes_on_data_keys_are_counted_and_dropped(tmp_path):
    with quick(tmp_path, "flood") as run, StatsWatcher(run, role="launcher") as stats:  # garbage from an insider who may send anything
        wait_version(stats, 1)
        rng = __import__("random").Random(0)
        for i in range(300):
            for key in (keys.traj("flood", i % 2), keys.obs("flood", i % 2), keys.act("flood", i % 2),
                        keys.weights("flood")):
                stats.session.put(key, bytes(rng.getrandbits(8) for _ in range(rng.randint(0, 64))))
        wrong_version = msgpack.packb({"v": 99, "reason": "a future schema"})
        stats.session.put(keys.ctl("flood", "train", 0, "stop"), wrong_version)  # must not stop train
        stats.session.put(keys.ctl("flood", "nosuch", 0, "stop"), msgpack.packb({"v": 1, "reason": "x"}))  # no such
        code = run.wait(FINISH_S)
    check_survived(stats, code)
    assert stats.latest("launcher/0", "launcher/ctl_unknown_service") == 1
    assert stats.latest("train/0", "bus/malformed", 0) > 0 and stats.latest("gen/0", "bus/malformed", 0) > 0
    assert stats.latest("sim/0", "bus/malformed", 0) > 0


@pytest.mark.slow
def test_resume_continues_a_stopped_run_with_the_version_counter(tmp_path):
    with up(tmp_path, "configs/quickstart.toml", "run.iterations=3", "train.batch_size=256", name="resumed") as run:
        assert run.wait(FINISH_S) == 0, run.output
    run_dir = run.run_dir
    assert (run_dir / "checkpoints" / "latest").read_text().strip() == "v00000003"
    cmd = [sys.executable, "-m", "ebrl.cli", "up", str(ROOT / "configs/quickstart.toml"), "--resume", str(run_dir),
           "--set", "run.name=resumed", "--set", "run.iterations=5", "--set", "train.batch_size=256",
           "--set", f"run.output_dir=\"{tmp_path}\""]
    proc = subprocess.run(cmd, cwd=ROOT, capture_output=True, text=True, timeout=FINISH_S)
    assert proc.returncode == 0, proc.stdout + proc.stderr
    assert f"resuming {run_dir} from v00000003" in proc.stdout and "5 iterations" in proc.stdout
    assert "resumed from" in (run_dir / "logs" / "train-0.log").read_text()
    assert (run_dir / "checkpoints" / "latest").read_text().strip() == "v00000005"
    assert len(list(tmp_path.glob("resumed-*"))) == 1  # the same run directory
    missing = subprocess.run([sys.executable, "-m", "ebrl.cli", "up", str(ROOT / "configs/quickstart.toml"),
                              "--resume", str(tmp_path / "nope")], capture_output=True, text=True, timeout=120)
    assert missing.returncode == 2 and "no checkpoint" in missing.stderr


@pytest.mark.slow
def test_two_runs_on_one_bus_never_see_each_others_data(tmp_path):
    # Run b joins run a's bus (an open bus: with each run's own secret they could not meet at all); the run
    # name in every key keeps them apart. Their observations differ in shape (InvertedPendulum 4, Hopper 11),
    # so a message of the other run would be counted as malformed.
    with quick(tmp_path / "a", "iso-a", "run.iterations=3", "bus.auth=false") as a, StatsWatcher(a) as stats_a, \
            quick(tmp_path / "b", "iso-b", "run.iterations=3", 'env.id="Hopper-v5"', "bus.auth=false",
                  f'bus.connect=["{a.endpoint}"]') as b, StatsWatcher(b) as stats_b:
        code_b = b.wait(FINISH_S)
        code_a = a.wait(FINISH_S)
    assert code_a == 0 and code_b == 0, a.output + b.output
    for stats in (stats_a, stats_b):
        assert stats.latest("train/0", "train/policy_version") == 3
        assert stats.latest("train/0", "train/segments_received") > 0
        assert all(r.metrics.get("bus/malformed", 0) == 0 for r in stats.reports())
