"""Each workload config runs as a real `ebrl up` for a few iterations; checkpoints carry a policy between runs;
ManiSkill without a GPU stops at once with a message that names the CPU configs."""

import pathlib
import subprocess
import sys

import pytest

from helpers import ROOT, run_collecting_stats
from test_metrics import assert_catalogued


def only_run_dir(root: pathlib.Path) -> pathlib.Path:
    (path,) = [p for p in root.iterdir() if p.is_dir() and p.name != "profiles"]
    return path


def test_grpo_config_trains(tmp_path):
    code, out, stats = run_collecting_stats(tmp_path / "runs", "configs/grpo_pendulum.toml", "run.iterations=3",
                                            "train.batch_size=64", run="grpo-e2e")
    assert code == 0, out
    train = stats["train/0"][-1]
    assert train["train/policy_version"] == 3 and train["train/grpo_groups"] >= 1
    assert train.get("train/grpo_groups_dropped_overflow", 0) == 0  # group-mates run their episodes together
    assert "train/value_loss" in train and train["train/value_loss"] == 0.0  # no critic is trained
    assert_catalogued(stats)  # GRPO's metrics are on docs/stats.md


@pytest.mark.slow
def test_flow_policy_trains_and_its_checkpoint_starts_the_next_run(tmp_path):
    code, out, stats = run_collecting_stats(tmp_path / "a", "configs/quickstart.toml", "run.iterations=2",
                                            'policy.kind="flow"', "policy.denoise_steps=3", "train.batch_size=256",
                                            run="flow-e2e")
    assert code == 0, out
    assert stats["train/0"][-1]["train/policy_version"] == 2
    checkpoint = only_run_dir(tmp_path / "a") / "policy.safetensors"
    assert checkpoint.is_file(), out
    code, out, stats = run_collecting_stats(tmp_path / "b", "configs/quickstart.toml", "run.iterations=1",
                                            'policy.kind="flow"', "policy.denoise_steps=5", "train.batch_size=256",
                                            f'policy.checkpoint="{checkpoint}"', run="flow-e2e2")
    assert code == 0, out  # N changed between runs: same parameters, the checkpoint loads
    log = (only_run_dir(tmp_path / "b") / "logs" / "train-0.log").read_text()
    assert f"from {checkpoint}" in log
    code, out, _ = run_collecting_stats(tmp_path / "c", "configs/quickstart.toml", "run.iterations=1",
                                        f'policy.checkpoint="{checkpoint}"', run="flow-e2e3")  # an mlp policy
    assert code != 0 and "checkpoint" in out and "kind" in out


@pytest.mark.slow
def test_robosuite_camera_config_trains(tmp_path):
    code, out, stats = run_collecting_stats(
        tmp_path / "runs", "configs/robosuite_lift_rgb.toml", "run.iterations=2", "train.batch_size=16",
        "sim.groups=1", "sim.envs_per_group=2", "policy.denoise_steps=2", "env.max_episode_steps=24", run="rgb-e2e",
        timeout=600)
    assert code == 0, out
    assert stats["train/0"][-1]["train/policy_version"] == 2
    assert "sim/success_rate" in stats["sim/0"][-1]


def test_maniskill_without_a_gpu_stops_at_once_naming_the_cpu_configs(tmp_path):
    from ebrl.envs import EnvSpec, preflight
    from ebrl.envs import EnvError

    try:
        preflight(EnvSpec("PickCube-v1", backend="maniskill"))
    except EnvError:
        pass
    else:
        pytest.skip("ManiSkill can run on this machine")
    # "at once": refused before anything starts (exit 2, no run directory); how many seconds the imports take
    # depends on the machine's load, so the deadline is only generous
    proc = subprocess.run([sys.executable, "-m", "ebrl.cli", "up", str(ROOT / "configs" / "maniskill.toml"),
                           "--set", f'run.output_dir="{tmp_path}"'], capture_output=True, text=True, timeout=180)
    assert proc.returncode == 2 and "Traceback" not in proc.stderr
    assert "ManiSkill needs a Vulkan-capable GPU" in proc.stderr and "configs/robosuite_lift.toml" in proc.stderr
    assert not list(tmp_path.iterdir())  # nothing started, no run directory


@pytest.mark.slow
def test_flow_policy_learns_the_quickstart_task(tmp_path):
    """The learning check of the flow-matching policy (BENCHMARKS.md): InvertedPendulum to a mean return of 900."""
    import json

    from helpers import up

    with up(tmp_path / "runs", "configs/quickstart.toml", 'policy.kind="flow"', name="flow-learn") as run:
        assert run.wait(900) == 0, run.output
    summary = json.loads((run.run_dir / "summary.json").read_text())
    assert summary["target_reached"] is not None, run.output
    assert summary["target_reached"]["return"] >= 900 and summary["target_reached"]["wall_s"] < 600
