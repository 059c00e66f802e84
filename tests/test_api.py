"""EBRL from Python (ebrl.api, ebrl.stats.stream), and the fast suite's end-to-end quickstart: a short script
trains the stock quickstart by name with ebrl.train while ebrl.watch, the plain zenoh subscriber (examples/subscribe_stats.py) and `ebrl
stats --json` follow it; config names and copies of the stock configs (ebrl configs, ebrl init)."""

from __future__ import annotations

import json
import os
import subprocess
import sys
import time
from pathlib import Path

import pytest

import ebrl
from ebrl import config
from ebrl.testing import Output, free_port
from helpers import ROOT
from test_up import check_tracking_outputs

# 3 updates of 512 decisions: training has taken more than the 1000 decisions after which it learns the reward
# bound ("auto", ebrl.algos.returns.LEARN_AFTER) before the run ends, so it counts the episodes (a run now ends on the
# update that reaches run.iterations; with 256 it counted none when the run ended at once)
SCRIPT = """\
import sys, ebrl
run = ebrl.train("quickstart", run={{"iterations": 3, "name": "e2e", "output_dir": sys.argv[1]}},
                 train={{"batch_size": 512}}, bus={{"listen": ["tcp/127.0.0.1:{port}"]}})
print("result", run.exit_code, run.summary["iterations"], run.policy_path, run.load_policy().chunk)
"""


def test_a_script_trains_with_ebrl_train_while_scripts_and_ebrl_stats_follow_the_run(tmp_path):
    """The quickstart by name from a short script (ebrl.train), followed three ways while it runs: ebrl.watch
    here, the plain zenoh subscriber (examples/subscribe_stats.py) and `ebrl stats --json`; then what
    the run leaves (summary, TensorBoard, metrics.csv, meta.json, the policy)."""
    script = tmp_path / "train.py"
    script.write_text(SCRIPT.format(port=free_port()))
    env = {**os.environ, "PYTHONPATH": str(ROOT)}
    proc = subprocess.Popen([sys.executable, str(script), str(tmp_path / "runs")], cwd=tmp_path, env=env,
                            stdout=subprocess.PIPE, stderr=subprocess.STDOUT, text=True)
    out, watchers = Output(proc, "the ebrl.train script"), []
    try:
        first = out.wait_for_line(lambda line: line.startswith("run e2e: "), 120, "the run's first line")
        run_dir = Path(first.split(": ", 1)[1].split("  (", 1)[0])
        out.wait_for_line(lambda line: "all services live" in line, 300, "every service live")
        watchers = [subprocess.Popen([sys.executable, *args], stdout=subprocess.PIPE, text=True, env=env) for args in
                    ([str(ROOT / "examples" / "subscribe_stats.py"), str(run_dir), "60"],
                     ["-m", "ebrl.cli", "stats", str(run_dir), "--json", "--count", "3"],
                     ["-m", "ebrl.cli", "stats", str(run_dir), "--json"])]  # this one until the run ends
        versions = [r.metrics["train/policy_version"] for r in ebrl.watch(run_dir, idle_timeout=120)
                    if r.service == "train"]  # it ends by itself when the run does
        assert proc.wait(120) == 0, out.text
        ended = time.monotonic()
        as_json, _ = watchers[1].communicate(timeout=60)
        to_the_end, _ = watchers[2].communicate(timeout=60)  # it ends by itself, as ebrl.watch does
        assert watchers[2].returncode == 0
        print(f"ebrl stats RUN_DIR --json ended {time.monotonic() - ended:.1f} s after the run's script")
    finally:
        for p in (proc, *watchers):
            p.kill()
    out.join()
    plain, _ = watchers[0].communicate()
    assert versions and max(versions) == 3 and versions == sorted(versions)
    lines = [json.loads(line) for line in as_json.splitlines()]
    assert len(lines) == 3 and all(line["key"].startswith("ebrl/stats/e2e/") for line in lines)
    followed = [json.loads(line) for line in to_the_end.splitlines()]
    assert any(line.get("service") == "train" and line["metrics"].get("train/policy_version") == 3 for line in followed)
    assert "e2e:" in plain and "env steps/s" in plain  # decoded stats reached a plain zenoh script
    assert len((ROOT / "examples" / "subscribe_stats.py").read_text().splitlines()) < 15  # docs/stats.md's promise
    text = out.text
    assert "run e2e finished: 3 iterations" in text
    assert "auto: policy.dtype = 'float32', gen.compile = 'off' (no GPU on this host)" in text
    result = text.splitlines()[-1].split()
    assert result[:3] == ["result", "0", "3"] and result[3].endswith("policy.safetensors") and result[4] == "4"
    summary = json.loads((run_dir / "summary.json").read_text())
    assert summary["iterations"] == 3 and summary["segments"] > 0 and summary["env_steps"] > 0
    check_tracking_outputs(run_dir, summary, command=("python", str(script)))


def test_a_run_that_cannot_start_raises_naming_the_field(tmp_path):
    with pytest.raises(ebrl.RunNotStarted, match="sim.groups"):
        ebrl.train("quickstart", sim={"groups": 0}, run={"output_dir": str(tmp_path)})
    with pytest.raises(TypeError, match="as a dict"):
        ebrl.train("quickstart", run=3)


def test_stock_configs_run_by_name_and_copy_with_their_bases(tmp_path):
    assert config.find("quickstart").read_text() == (ROOT / "configs" / "quickstart.toml").read_text()
    assert config.load("quickstart.toml").run.name == "quickstart"
    with pytest.raises(config.ConfigError, match="stock configs: .*quickstart"):
        config.find("quikstart")
    written = config.copy_stock("bench_lift", tmp_path)
    assert [p.name for p in written] == ["bench_lift.toml", "robosuite_lift.toml"]  # its base comes along
    assert config.load(written[0]).env.id == config.load("bench_lift").env.id
    with pytest.raises(config.ConfigError, match="already exists"):
        config.copy_stock("bench_lift", tmp_path)
    listed = subprocess.run([sys.executable, "-m", "ebrl.cli", "configs"], capture_output=True, text=True,
                            cwd=ROOT, check=True).stdout
    assert listed.splitlines()[0].split()[0] in config.stock_configs() and "quickstart" in listed
    from ebrl.cli import first_sentence

    for name, path in config.stock_configs().items():  # each described by a whole sentence, none cut short
        described = first_sentence(path.read_text())
        assert described.endswith(".") and " ".join(described.split()) in " ".join(listed.split()), name
