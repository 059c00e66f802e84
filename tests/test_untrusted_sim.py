"""The simulator is untrusted (issue 52): what a process signed in with the simulator's own line sends on the
simulator's own keys cannot end a run as reached, halt it or fail it. Here: episode values forged in segments
(tests/forging_sim.py), against a live quickstart with its own target return (900). The other cases of the
hostile suite (fake instances, a flood of frozen reports, an oversized observation) are in tests/test_auth.py."""

from __future__ import annotations

import json
import os
import subprocess
import sys

from ebrl.testing import StatsWatcher
from helpers import ROOT, up


def test_episode_returns_forged_in_a_simulator_s_segments_never_reach_the_run_s_numbers(tmp_path):
    """For the whole run the forger sends, 5 times a second, segments whose rewards sum to 44 claiming 20 episodes
    of 5000, one of 5000, an episode that did not end, and replays: training refuses them all (counted), the run
    finishes every iteration with no restart, reaches nothing it did not, and every return it shows is a real
    one (InvertedPendulum returns at most 1000)."""
    env = {**os.environ, "PYTHONPATH": str(ROOT)}
    with up(tmp_path, "configs/quickstart.toml", "run.iterations=30", 'viz.rerun="off"', name="forger") as run:
        run.wait_for_line("all services live", 300)
        forger = subprocess.Popen([sys.executable, str(ROOT / "tests" / "forging_sim.py"), run.endpoint, run.name,
                                   str(run.run_dir)], stdin=subprocess.PIPE, stdout=subprocess.PIPE, text=True,
                                  env=env)
        with StatsWatcher(run) as stats:
            code = run.wait(400)
        out = json.loads(forger.communicate("", timeout=120)[0])
    assert code == 0, run.output[-4000:]
    assert out["routers"] == 1 and out["sent"] > 10 * out["kinds"], out  # signed in, and kept at it
    summary = json.loads((run.run_dir / "summary.json").read_text())
    assert summary["iterations"] == 30 and summary["restarts"] == {}, summary
    refused = stats.latest("train/0", "train/episode_values_refused", 0)
    assert refused > 0 and stats.latest("train/0", "train/segments_replayed", 0) > 0
    returns = stats.values("train/0", "train/episode_return_mean")
    assert all(r <= 1000.0 for r in returns), max(returns)
    if summary["target_reached"] is not None:  # only the real policy may reach it, with a return it made
        assert summary["target_reached"]["return"] <= 1000.0
    for value in (summary["final_return"], summary["best_return"]):
        assert value is None or value <= 1000.0, summary
    report = (run.run_dir / "report" / "report.md").read_text()
    assert "train/episode_values_refused" in report  # where a user sees it
