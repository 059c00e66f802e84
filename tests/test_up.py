"""End to end: real `ebrl up` runs on loopback (services are separate processes talking over Zenoh)."""

import json
import pathlib
import signal
import subprocess
import sys
import time

import psutil
import pytest

import helpers

ROOT = pathlib.Path(__file__).resolve().parent.parent


def ebrl_up(tmp_path, *overrides, port=None):
    return helpers.ebrl_up(tmp_path, "configs/quickstart.toml", *overrides, port=port)


def run_dir(tmp_path) -> pathlib.Path:
    (path,) = [p for p in tmp_path.iterdir() if p.is_dir()]
    return path


def test_two_iterations_train_and_the_readme_subscriber_sees_stats(tmp_path):
    proc, port = ebrl_up(tmp_path / "runs", "run.iterations=2", "run.name=e2e")
    watcher = subprocess.Popen([sys.executable, str(ROOT / "examples" / "subscribe_stats.py"),
                                f"tcp/127.0.0.1:{port}", "60"], stdout=subprocess.PIPE, text=True)
    cli = subprocess.Popen([sys.executable, "-m", "ebrl.cli", "stats", "--run", "e2e", "--count", "3",
                            "--connect", f"tcp/127.0.0.1:{port}"], stdout=subprocess.PIPE, text=True)
    try:
        out, _ = proc.communicate(timeout=120)
        printed, _ = cli.communicate(timeout=10)
    finally:
        watcher.kill()
        cli.kill()
    lines, _ = watcher.communicate()
    assert printed.count("ebrl/stats/e2e/") == 3 and "proc/rss_mb=" in printed  # `ebrl stats` decoded them
    assert proc.returncode == 0, out
    assert "all services live" in out and "run e2e finished: 2 iterations" in out
    summary = json.loads((run_dir(tmp_path / "runs") / "summary.json").read_text())
    assert summary["iterations"] == 2 and summary["segments"] > 0 and summary["env_steps"] > 0
    assert "e2e:" in lines and "env steps/s" in lines  # decoded stats reached a plain zenoh script
    assert len((ROOT / "examples" / "subscribe_stats.py").read_text().splitlines()) < 15  # README's promise


def test_weights_versions_advance_and_trajectories_flow(tmp_path):
    code, out, seen = helpers.run_collecting_stats(tmp_path / "runs", "configs/quickstart.toml", "run.iterations=3",
                                                   run="flow")
    assert code == 0, out
    gen_versions = [m["gen/policy_version"] for m in seen["gen/0"]]
    assert gen_versions == sorted(gen_versions) and gen_versions[-1] >= 2  # gen applied new weights
    train = seen["train/0"][-1]
    assert train["train/policy_version"] == 3 and train["train/segments_received"] > 0
    sim = seen["sim/0"][-1]
    assert sim["sim/segments"] >= train["train/segments_received"] > 0
    assert all(m.get("bus/malformed", 0) == 0 for ms in seen.values() for m in ms)


def test_services_are_separate_processes_and_sigint_leaves_none(tmp_path):
    proc, port = ebrl_up(tmp_path / "runs", "run.iterations=0", "run.name=sigint")
    launcher = psutil.Process(proc.pid)
    deadline = time.monotonic() + 90
    line = ""
    while "all services live" not in line:
        line = proc.stdout.readline()
        assert line and time.monotonic() < deadline, "services never came up"
    time.sleep(2)  # let it train a little
    tree = launcher.children(recursive=True)
    roles = {p.cmdline()[2] for p in launcher.children() if len(p.cmdline()) > 2}
    assert roles == {"services.sim", "services.gen", "services.train"}
    assert len(tree) >= 3 + 8  # three services plus one worker process per environment
    proc.send_signal(signal.SIGINT)
    start = time.monotonic()
    proc.wait(timeout=15)
    gone, alive = psutil.wait_procs(tree, timeout=max(0.1, 10 - (time.monotonic() - start)))
    assert not alive, f"left behind: {[p.pid for p in alive]}"
    assert time.monotonic() - start < 10
    assert proc.returncode == 130


@pytest.mark.slow
def test_quickstart_learns_to_the_stated_return(tmp_path):
    proc, _ = ebrl_up(tmp_path / "runs", "run.name=learn")
    out, _ = proc.communicate(timeout=900)
    assert proc.returncode == 0, out
    summary = json.loads((run_dir(tmp_path / "runs") / "summary.json").read_text())
    assert summary["target_reached"] is not None, out
    assert summary["target_reached"]["return"] >= 900
    assert summary["target_reached"]["wall_s"] < 600


def test_a_service_that_fails_is_reported_and_the_run_stops(tmp_path):
    proc, _ = ebrl_up(tmp_path / "runs", "run.name=broken", "env.id=NoSuchEnv-v9")
    out, _ = proc.communicate(timeout=120)
    assert proc.returncode == 1
    assert "exited with status" in out and "NoSuchEnv-v9" in out  # the dead service's last log lines
