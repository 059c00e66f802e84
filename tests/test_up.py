"""End to end: real `ebrl up` runs on loopback (services are separate processes talking over Zenoh)."""

import json
import time

import psutil
import pytest

import helpers
from ebrl.supervisor import SHUTDOWN_S
from test_metrics import assert_catalogued

ROOT = helpers.ROOT
LOADED_S = 22.0  # slack for a loaded machine on top of the launcher's own deadlines


def quickstart(tmp_path, *overrides, name: str) -> helpers.Run:
    return helpers.up(tmp_path, "configs/quickstart.toml", *overrides, name=name)


# The fast suite's end-to-end quickstart (versions advance, examples/subscribe_stats.py, `ebrl stats`, what the run
# leaves) is tests/test_api.py's, started from Python as a user's script would.


def check_tracking_outputs(run_dir, summary, command=("ebrl", "up")) -> None:
    """What the log service, the launcher and the report leave: TensorBoard curves keyed by env steps, metrics.csv,
    meta.json, report/learning.png."""
    from tensorboard.backend.event_processing.event_accumulator import EventAccumulator

    acc = EventAccumulator(str(run_dir / "tb"))
    acc.Reload()
    returns = acc.Scalars("episode/return")
    assert len(returns) >= summary["episodes"] > 0  # every episode (sim's last batch may land after the summary)
    assert all(0 < e.step <= summary["sim"]["env_steps"] for e in returns)  # episodes sit at the sims' env steps
    assert [e.step for e in returns] == sorted(e.step for e in returns)
    assert {"sim/episode_return_mean", "train/policy_loss", "train/value_loss", "train/approx_kl",
            "train/staleness_mean", "run/env_steps"} <= set(acc.Tags()["scalars"])
    rows = (run_dir / "metrics.csv").read_text().splitlines()
    assert rows[0] == "step,wall_time,key,value" and sum(",episode/return," in r for r in rows) == len(returns)
    meta = json.loads((run_dir / "meta.json").read_text())
    assert meta["command"][:len(command)] == list(command) and meta["packages"]["torch"] and meta["seeds"]["run"] == 1
    # no GPU here: "auto" became float32 and eager without a measurement, and the services ran what config.toml says
    assert meta["auto"]["settings"] == {"policy.dtype": "float32", "gen.compile": "off"}, meta["auto"]
    assert 'dtype = "float32"' in (run_dir / "config.toml").read_text()
    assert (run_dir / "report" / "learning.png").stat().st_size > 20_000


def test_weights_versions_advance_and_trajectories_flow(tmp_path):
    code, out, seen = helpers.run_collecting_stats(tmp_path / "runs", "configs/quickstart.toml", "run.iterations=3",
                                                   run="flow")
    assert code == 0, out
    gen_versions = [m["gen/policy_version"] for m in seen["gen/0"]]
    assert gen_versions == sorted(gen_versions) and gen_versions[-1] >= 2  # gen applied new weights
    assert (seen["gen/0"][-1]["gen/dtype"], seen["gen/0"][-1]["gen/compiled"], seen["train/0"][-1]["train/dtype"]) \
        == (32.0, 0.0, 32.0)  # what "auto" became here (ebrl.autotune), in the stats
    train = seen["train/0"][-1]
    assert train["train/policy_version"] == 3 and train["train/segments_received"] > 0
    sim = seen["sim/0"][-1]
    assert sim["sim/segments"] >= train["train/segments_received"] > 0
    assert all(m.get("bus/malformed", 0) == 0 for ms in seen.values() for m in ms)
    assert_catalogued(seen)  # every metric it published is on docs/stats.md, the launcher's and log's too


def test_services_run_in_the_planned_processes_and_sigint_leaves_none(tmp_path):
    with quickstart(tmp_path / "runs", "run.iterations=0", name="sigint") as run:
        launcher = psutil.Process(run.proc.pid)
        run.wait_for_line("all services live", 300)
        deadline = time.monotonic() + 120
        # train, log, sim and gen in one (this CPU host's "auto"), the env workers' forkserver, one worker per env
        while len(launcher.children(recursive=True)) < 3 + 1 + 8:
            assert time.monotonic() < deadline, f"processes: {launcher.children(recursive=True)}"
            time.sleep(0.2)
        time.sleep(2)  # let it train a little
        tree = launcher.children(recursive=True)
        started = {" ".join(argv[2:3] + [b for a, b in zip(argv, argv[1:]) if a == "--service"])
                   for argv in (p.cmdline() for p in launcher.children()) if len(argv) > 2}
        assert started == {"ebrl.process gen/0 sim/0", "ebrl.services.train", "ebrl.services.log"}, started
        run.interrupt()
        start = time.monotonic()
        code = run.wait(SHUTDOWN_S + LOADED_S)
        gone, alive = psutil.wait_procs(tree, timeout=max(0.1, SHUTDOWN_S + LOADED_S - (time.monotonic() - start)))
    assert not alive, f"left behind: {[p.pid for p in alive]}"
    assert time.monotonic() - start < SHUTDOWN_S + LOADED_S  # the launcher kills what is left after SHUTDOWN_S
    assert code == 130


@pytest.mark.slow  # 11 s: the fast suite keeps to its 10 minutes on 2 cores
def test_ctrl_c_while_the_services_start_is_a_stop_not_a_failure(tmp_path):
    """SIGINT as soon as the launcher has started the services (they take seconds to import torch): the run
    stops with 130, as after Ctrl-C later, and its summary names no failure (it said exit 1 before)."""
    with quickstart(tmp_path / "runs", "run.iterations=0", name="early") as run:
        run.wait_for_line("run early:", 300)  # printed before any service starts
        run.interrupt()
        code = run.wait(SHUTDOWN_S + LOADED_S)
    assert "all services live" not in run.output, "the services were up before the SIGINT reached the launcher"
    assert code == 130, run.output
    assert json.loads((run.run_dir / "summary.json").read_text())["failure"] is None


@pytest.mark.slow
def test_quickstart_learns_to_the_stated_return(tmp_path):
    with quickstart(tmp_path / "runs", name="learn") as run:
        assert run.wait(900) == 0, run.output
    summary = json.loads((run.run_dir / "summary.json").read_text())
    assert summary["target_reached"] is not None, run.output
    assert summary["target_reached"]["return"] >= 900
    assert summary["target_reached"]["wall_s"] < 600


def test_a_service_that_fails_is_reported_and_the_run_stops(tmp_path):
    with quickstart(tmp_path / "runs", "env.id=NoSuchEnv-v9", name="broken") as run:
        code = run.wait(300)
    assert code == 1
    assert "exited with status" in run.output and "NoSuchEnv-v9" in run.output  # the dead service's last log lines
