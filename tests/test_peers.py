"""The outside peers of the benchmarks run (a short smoke run each; the comparisons are in benchmarks/)."""

import json
import subprocess
import sys

import pytest

from helpers import ROOT


@pytest.mark.slow
def test_cleanrl_style_ppo_peer_runs_learns_and_writes_json(tmp_path):
    out = tmp_path / "peer.json"
    proc = subprocess.run([sys.executable, "benchmarks/peers/cleanrl_ppo.py", "--env", "InvertedPendulum-v5",
                           "--num-envs", "8", "--target-return", "900", "--max-seconds", "20", "--seed", "0",
                           "--json", str(out)], cwd=ROOT, capture_output=True, text=True, timeout=180)
    assert proc.returncode == 0, proc.stderr[-3000:]
    result = json.loads(out.read_text())
    summary = result["summary"]
    assert summary["stop_reason"] == "max_seconds" and summary["env_steps"] > 5000 and summary["updates"] >= 2
    assert result["hyperparameters"]["action_chunk"] == 1 and "command" in result
