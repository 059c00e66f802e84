"""The eval service in real runs: `ebrl up` with eval.every > 0 (real processes, real Zenoh, the quickstart env)."""

import json
import os
import subprocess
import sys
import time

import imageio
import psutil
import pytest

import ebrl
import helpers
from ebrl.policies.checkpoint import read_metadata
from ebrl.viz import record
from test_metrics import assert_catalogued
from test_portable import SCRIPT

EVAL_NAMES = {"eval/return", "eval/return_lo", "eval/return_hi", "eval/episode_length", "eval/version"}


def eval_reports(run_dir):
    """The eval service's result reports, from the run's recording of every stats report."""
    rec = record.read(run_dir / record.FILENAME)
    return [r for r in rec.stats if r.service == "eval" and "eval/version" in r.metrics]


@pytest.mark.slow  # 22 s: the fast suite keeps to its 10 minutes on 2 cores
def test_up_with_eval_reports_each_version_records_videos_and_keeps_the_best_policy(tmp_path):
    with helpers.up(tmp_path / "runs", "configs/quickstart.toml", "run.iterations=4", "eval.every=2",
                    "eval.episodes=3", name="evalrun") as run:
        code = run.wait(300)
    out, run_dir = run.output, run.run_dir
    assert code == 0, out
    live_line = out.split("all services live")[1].splitlines()[0]
    assert "eval/0" not in live_line and "train/0" in live_line  # optional: the run never waits for eval to start
    assert "waiting for the evaluation of the final policy v4" in out and "eval v4: return" in out
    reports = eval_reports(run_dir)
    versions = [int(r.metrics["eval/version"]) for r in reports]
    assert versions[-1] == 4 and set(versions) <= {2, 4}  # v2 may be dropped for v4 on a busy machine
    for r in reports:
        assert EVAL_NAMES <= set(r.metrics) and r.metrics["eval/return_lo"] <= r.metrics["eval/return"]
        assert r.metrics["eval/episodes"] == 3.0 and "eval/success_rate" not in r.metrics  # no success in this env
    summary = json.loads((run_dir / "summary.json").read_text())
    assert summary["last_eval"]["eval/version"] == 4.0
    assert_catalogued(record.read(run_dir).stats)  # every metric of the run (eval's among them) is on docs/stats.md
    for version in versions:
        video = run_dir / "videos" / f"v{version}" / "episode-0.mp4"
        assert len([frame for frame in imageio.get_reader(video)]) > 1
    best = ebrl.load_policy(run_dir, which="best")
    scores = {int(r.metrics["eval/version"]): r.metrics["eval/return"] for r in reports}
    assert best.version == max(scores, key=lambda v: (scores[v], -v))  # the best return, the first to reach it
    assert float(read_metadata(str(run_dir / "best.safetensors"))["eval_return"]) == scores[best.version]
    # the evaluation of v4 repeats exactly outside the run: same policy, same held-out seeds, deterministic
    latest = ebrl.load_policy(run_dir)
    assert latest.version == 4
    from ebrl.evaluate import run_episodes

    assert run_episodes(latest, 3).summary()["return"]["mean"] == scores[4]


@pytest.mark.slow  # an optional service's death; eval itself runs in the fast suite (here and tests/test_in_process.py)
def test_an_eval_service_that_dies_never_stops_the_run(tmp_path):
    with helpers.up(tmp_path / "runs", "configs/quickstart.toml", "run.iterations=5", "eval.every=1",
                    "eval.episodes=2", "eval.video_episodes=0", "run.max_restarts=0", name="evaldies") as run:
        run.wait_for_line("all services live", 300)
        launcher = psutil.Process(run.proc.pid)
        evaluator = next(p for p in launcher.children() if "ebrl.services.eval" in p.cmdline())
        deadline = time.monotonic() + 120
        while not (workers := evaluator.children(recursive=True)):  # started with the first evaluation
            assert time.monotonic() < deadline, run.output
            time.sleep(0.2)
        evaluator.kill()  # its workers die with it (PR_SET_PDEATHSIG)
        code = run.wait(300)
    assert code == 0, run.output
    assert "eval/0 exited with status -9; the run goes on without it" in run.output
    assert "run evaldies finished: 5 iterations" in run.output
    assert "waiting for the evaluation" not in run.output  # nothing waits for a dead eval service
    _, alive = psutil.wait_procs(workers, timeout=10)
    assert not alive, f"eval workers left behind: {alive}"


@pytest.mark.slow
def test_the_trained_quickstart_policy_reaches_the_reported_return_in_a_ten_line_script(tmp_path):
    """The issue's acceptance: a 10-line script with ebrl.load_policy plays the trained quickstart policy in a plain
    gymnasium loop and reaches the return the run reported (deterministic, within 5 %)."""
    with helpers.up(tmp_path / "runs", "configs/quickstart.toml", "eval.every=50", name="evallearn") as run:
        assert run.wait(900) == 0, run.output
    summary = json.loads((run.run_dir / "summary.json").read_text())
    assert summary["target_reached"] is not None, run.output
    script = tmp_path / "play.py"
    script.write_text(SCRIPT)
    env = dict(os.environ, PYTHONPATH=str(helpers.ROOT))
    played = subprocess.run([sys.executable, str(script), str(run.run_dir)], capture_output=True, text=True,
                            timeout=300, env=env)
    assert played.returncode == 0, played.stderr
    assert float(played.stdout.split()[-1]) >= 0.95 * summary["final_return"]
    evaluated = subprocess.run([sys.executable, "-m", "ebrl.cli", "eval", str(run.run_dir), "--episodes", "10"],
                               capture_output=True, text=True, timeout=600, env=env)
    assert evaluated.returncode == 0, evaluated.stderr
    print(evaluated.stdout)
    report = json.loads((run.run_dir / "eval.json").read_text())
    assert report["return"]["mean"] >= 0.95 * summary["final_return"]
