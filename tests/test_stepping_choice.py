"""The stepping choice in a real run (``sim.core_rebinding = "auto"``, the ebrl default): it decides once the
run is in its steady state, and decides again when the env's step cost changes mid-run (issue 36). Which mode
wins on this machine is not asserted -- that depends on its load; the choice's logic over given rates is
tested with a fake clock in tests/test_corepool.py."""

from __future__ import annotations

import os
import re
import time
from pathlib import Path

import pytest

from ebrl.testing import Run, StatsWatcher

HERE = Path(__file__).resolve().parent
ROOT = HERE.parent
CORES = sorted(os.sched_getaffinity(0))


@pytest.mark.slow
@pytest.mark.skipif(len(CORES) < 2, reason="rebinding needs 2 cores to hand between envs")
def test_a_step_cost_that_changes_mid_run_is_followed_by_a_new_decision(tmp_path, monkeypatch):
    monkeypatch.setenv("PYTHONPATH", str(HERE))  # the user's env package
    marker = tmp_path / "slow-now"
    with Run(ROOT / "configs" / "bench_stepping.toml", "run.iterations=0", "env.latency=\"none\"",
             'env.id="phase_envs:MarkerLatency-v0"', f'env.kwargs.marker="{marker}"', "viz.report=false",
             name="phase", out_dir=tmp_path / "runs", stats_interval=1.0) as run, StatsWatcher(run) as stats:
        decisions = lambda: stats.latest("sim/0", "sim/stepping_decisions", 0.0)  # noqa: E731
        stats.wait_for(lambda: decisions() >= 1, 300, "the first stepping decision (0.1 ms steps)")
        time.sleep(3)  # the choice takes its latency reference at its next look (each second)
        first = stats.latest("sim/0", "sim/step_latency_p50_ms")
        marker.touch()  # from now on: heavy-tailed steps of 3 ms on average
        stats.wait_for(lambda: decisions() >= 2, 300, "a new decision after the step cost changed")
        assert stats.latest("sim/0", "sim/step_latency_p50_ms") > 5 * first
        assert run.stop() == 130
    log = (run.run_dir / "logs" / "sim-0.log").read_text()
    lines = re.findall(r"stepping: (.*)", log)
    assert len(lines) >= 2 and "(start-up)" in lines[0], lines
    assert "moved" in lines[1] and "steps/s" in lines[1], lines  # the reason, and the rates behind the decision
