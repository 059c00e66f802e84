"""EBRL from Python (ebrl.api, ebrl.stats.stream): a short script trains the stock quickstart by name with
ebrl.train while this process follows the run with ebrl.watch and `ebrl stats --json`; config names and
copies of the stock configs (ebrl configs, ebrl init)."""

from __future__ import annotations

import json
import subprocess
import sys

import pytest

import ebrl
from ebrl import config
from ebrl.testing import Output, free_port
from helpers import ROOT

SCRIPT = """\
import sys, ebrl
run = ebrl.train("quickstart", run={{"iterations": 4, "output_dir": sys.argv[1]}}, train={{"batch_size": 256}},
                 viz={{"rerun": "off"}}, bus={{"listen": ["tcp/127.0.0.1:{port}"]}})
print("result", run.exit_code, run.summary["iterations"], run.policy_path, run.load_policy().chunk)
"""


def test_a_script_trains_with_ebrl_train_while_ebrl_watch_follows_the_run(tmp_path):
    script = tmp_path / "train.py"
    script.write_text(SCRIPT.format(port=free_port()))
    proc = subprocess.Popen([sys.executable, str(script), str(tmp_path / "runs")], cwd=tmp_path,
                            env={"PYTHONPATH": str(ROOT), "PATH": "/usr/bin:/bin"}, stdout=subprocess.PIPE,
                            stderr=subprocess.STDOUT, text=True)
    out = Output(proc, "the ebrl.train script")
    try:
        first = out.wait_for_line(lambda line: line.startswith("run quickstart: "), 120, "the run's first line")
        run_dir = first.split(": ", 1)[1].split("  (", 1)[0]
        out.wait_for_line(lambda line: "all services live" in line, 300, "every service live")
        versions, as_json = [], None
        for report in ebrl.watch(run_dir, idle_timeout=120):  # ends by itself when the run does
            if report.service == "train":
                versions.append(report.metrics["train/policy_version"])
            if as_json is None:
                as_json = subprocess.run([sys.executable, "-m", "ebrl.cli", "stats", run_dir, "--json", "--count",
                                          "2"], capture_output=True, text=True, timeout=120, cwd=ROOT)
        assert proc.wait(120) == 0, out.text
    finally:
        if proc.poll() is None:
            proc.kill()
    out.join()
    assert versions and max(versions) == 4 and versions == sorted(versions)
    assert as_json.returncode == 0, as_json.stderr
    lines = [json.loads(line) for line in as_json.stdout.splitlines()]
    assert len(lines) == 2 and all(line["key"].startswith("ebrl/stats/quickstart/") for line in lines)
    result = out.text.splitlines()[-1].split()
    assert result[:3] == ["result", "0", "4"] and result[3].endswith("policy.safetensors") and result[4] == "4"


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
