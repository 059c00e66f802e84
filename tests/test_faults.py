"""Fault injection into real `ebrl up` runs on loopback: each fault is survived, versions stay monotonic,
and the run finishes its iterations.

Faults: kill -9 an env worker mid-run; hang one (SIGSTOP); kill -9 gen; kill -9 train (it resumes from its
checkpoint); flood data keys with random bytes. And `ebrl up --resume RUN_DIR` continues a stopped run.
"""

import json
import signal
import subprocess
import sys
import threading
import time

import msgpack
import psutil
import pytest
import zenoh

from helpers import ROOT, ebrl_up

QUICK = ("run.iterations=8", "train.batch_size=256", "train.checkpoint_every=1")


class Watched:
    """A real `ebrl up` with every stats report collected as it arrives."""

    def __init__(self, out_dir, run, *overrides, config="configs/quickstart.toml"):
        self.run = run
        self.proc, self.port = ebrl_up(out_dir, config, f"run.name={run}", *QUICK, *overrides)
        conf = zenoh.Config()
        conf.insert_json5("scouting/multicast/enabled", "false")
        conf.insert_json5("connect/endpoints", f'["tcp/127.0.0.1:{self.port}"]')
        self.session = zenoh.open(conf)
        self.lock = threading.Lock()
        self.seen: dict[str, list[dict]] = {}
        self.session.declare_subscriber(f"ebrl/stats/{run}/**", self._on_sample)

    def _on_sample(self, sample) -> None:
        key = str(sample.key_expr).split("/", 3)[3]
        if not key.startswith(("spans/", "events/")):
            with self.lock:
                self.seen.setdefault(key, []).append(msgpack.unpackb(sample.payload.to_bytes())["metrics"])

    def last(self, service: str, metric: str, default=None):
        with self.lock:
            reports = self.seen.get(service, [])
            return next((m[metric] for m in reversed(reports) if metric in m), default)

    def values(self, service: str, metric: str) -> list[float]:
        with self.lock:
            return [m[metric] for m in self.seen.get(service, []) if metric in m]

    def wait_version(self, version: int, timeout: float = 120) -> None:
        deadline = time.monotonic() + timeout
        while (self.last("train/0", "train/policy_version") or 0) < version:
            assert self.proc.poll() is None, self.proc.stdout.read()
            assert time.monotonic() < deadline, f"no policy v{version} after {timeout} s"
            time.sleep(0.2)

    def service(self, role: str) -> psutil.Process:
        for child in psutil.Process(self.proc.pid).children():
            if f"services.{role}" in " ".join(child.cmdline()):
                return child
        raise AssertionError(f"no {role} service running")

    def env_workers(self) -> list[psutil.Process]:
        forkservers = [p for p in self.service("sim").children() if "forkserver" in " ".join(p.cmdline())]
        return [w for f in forkservers for w in f.children()]

    def finish(self, timeout: float = 240) -> tuple[int, str]:
        try:
            out, _ = self.proc.communicate(timeout=timeout)
        finally:
            if self.proc.poll() is None:
                self.proc.kill()
            self.session.close()
        return self.proc.returncode, out


def monotonic(values) -> bool:
    return all(b >= a for a, b in zip(values, values[1:]))


def check_survived(run: "Watched", code: int, out: str) -> None:
    """The run finished its iterations; versions never went back; nothing malformed or acted by an unknown
    version reached training."""
    assert code == 0, out
    assert run.last("train/0", "train/policy_version") == 8
    assert monotonic(run.values("train/0", "train/policy_version"))
    assert run.last("train/0", "train/future_version_dropped", 0) == 0


def test_a_killed_env_worker_is_replaced_and_the_others_keep_running(tmp_path):
    run = Watched(tmp_path, "kill-worker")
    run.wait_version(2)
    workers = run.env_workers()
    assert len(workers) == 8
    workers[3].send_signal(signal.SIGKILL)
    code, out = run.finish()
    check_survived(run, code, out)
    assert run.last("sim/0", "sim/worker_restarts") == 1
    assert monotonic(run.values("gen/0", "gen/policy_version"))
    assert run.last("train/0", "bus/malformed", 0) == 0  # nothing half-built reached training


@pytest.mark.slow
def test_a_hung_env_worker_is_killed_after_the_step_timeout(tmp_path):
    run = Watched(tmp_path, "hang-worker", "sim.step_timeout=2.0")
    run.wait_version(2)
    hung = run.env_workers()[5]
    hung.send_signal(signal.SIGSTOP)
    code, out = run.finish()
    check_survived(run, code, out)
    assert run.last("sim/0", "sim/worker_restarts") == 1
    assert not hung.is_running() or hung.status() == psutil.STATUS_ZOMBIE  # killed, not left stopped


def test_a_killed_gen_is_restarted_and_every_group_is_served_again(tmp_path):
    run = Watched(tmp_path, "kill-gen")
    run.wait_version(2)
    run.service("gen").send_signal(signal.SIGKILL)
    code, out = run.finish()
    check_survived(run, code, out)
    assert "gen/0 exited with status -9; restarting it" in out
    assert run.last("launcher/0", "launcher/restarts_gen") == 1
    summary = json.loads(next(tmp_path.glob("kill-gen-*/summary.json")).read_text())
    assert summary["restarts"] == {"gen/0": 1}


def test_a_killed_train_resumes_from_its_checkpoint_with_versions_never_reused(tmp_path):
    run = Watched(tmp_path, "kill-train")
    run.wait_version(3)
    run.service("train").send_signal(signal.SIGKILL)
    code, out = run.finish()
    check_survived(run, code, out)
    assert "train/0 exited with status -9; restarting it" in out
    assert monotonic(run.values("gen/0", "gen/policy_version"))  # gen never went back to an older version
    log = next(tmp_path.glob("kill-train-*/logs/train-0.log")).read_text()
    assert "resumed from" in log and "checkpoints/v" in log


def test_random_bytes_on_data_keys_are_counted_and_dropped(tmp_path):
    run = Watched(tmp_path, "flood")
    run.wait_version(1)
    rng = __import__("random").Random(0)
    for i in range(300):
        for key in (f"ebrl/data/flood/traj/{i % 2}", f"ebrl/data/flood/obs/{i % 2}", f"ebrl/data/flood/act/{i % 2}",
                    "ebrl/data/flood/weights"):
            run.session.put(key, bytes(rng.getrandbits(8) for _ in range(rng.randint(0, 64))))
    wrong_version = msgpack.packb({"v": 99, "reason": "a future schema"})
    run.session.put("ebrl/ctl/flood/train/0/stop", wrong_version)  # must not stop train
    run.session.put("ebrl/ctl/flood/nosuch/0/stop", msgpack.packb({"v": 1, "reason": "x"}))  # no such service
    code, out = run.finish()
    check_survived(run, code, out)
    assert run.last("launcher/0", "launcher/ctl_unknown_service") == 1
    assert run.last("train/0", "bus/malformed", 0) > 0 and run.last("gen/0", "bus/malformed", 0) > 0
    assert run.last("sim/0", "bus/malformed", 0) > 0


def test_resume_continues_a_stopped_run_with_the_version_counter(tmp_path):
    proc, _ = ebrl_up(tmp_path, "configs/quickstart.toml", "run.name=resumed", "run.iterations=3",
                      "train.batch_size=256")
    out, _ = proc.communicate(timeout=180)
    assert proc.returncode == 0, out
    (run_dir,) = tmp_path.glob("resumed-*")
    assert (run_dir / "checkpoints" / "latest").read_text().strip() == "v00000003"
    cmd = [sys.executable, "-m", "ebrl.cli", "up", str(ROOT / "configs/quickstart.toml"), "--resume", str(run_dir),
           "--set", "run.name=resumed", "--set", "run.iterations=5", "--set", "train.batch_size=256",
           "--set", f"run.output_dir=\"{tmp_path}\""]
    proc = subprocess.run(cmd, cwd=ROOT, capture_output=True, text=True, timeout=180)
    assert proc.returncode == 0, proc.stdout + proc.stderr
    assert f"resuming {run_dir} from v00000003" in proc.stdout and "5 iterations" in proc.stdout
    assert "resumed from" in (run_dir / "logs" / "train-0.log").read_text()
    assert (run_dir / "checkpoints" / "latest").read_text().strip() == "v00000005"
    assert len(list(tmp_path.glob("resumed-*"))) == 1  # the same run directory
    missing = subprocess.run([sys.executable, "-m", "ebrl.cli", "up", str(ROOT / "configs/quickstart.toml"),
                              "--resume", str(tmp_path / "nope")], capture_output=True, text=True, timeout=60)
    assert missing.returncode == 2 and "no checkpoint" in missing.stderr


@pytest.mark.slow
def test_two_runs_on_one_bus_never_see_each_others_data(tmp_path):
    # Run b joins run a's bus; the run name in every key keeps them apart. Their observations differ in shape
    # (InvertedPendulum 4, Hopper 11), so a message of the other run would be counted as malformed.
    a = Watched(tmp_path / "a", "iso-a", "run.iterations=3")
    b = Watched(tmp_path / "b", "iso-b", "run.iterations=3", 'env.id="Hopper-v5"',
                f'bus.connect=["tcp/127.0.0.1:{a.port}"]')
    code_b, out_b = b.finish()
    code_a, out_a = a.finish()
    assert code_a == 0 and code_b == 0, out_a + out_b
    for run in (a, b):
        assert run.last("train/0", "train/policy_version") == 3
        assert run.last("train/0", "train/segments_received") > 0
        assert all(m.get("bus/malformed", 0) == 0 for ms in run.seen.values() for m in ms)
