"""The MuJoCo Warp peer (benchmarks/peers/mjwarp_ppo.py): its defaults are EBRL's config for the race, and it runs
end to end on Warp's CPU device, partial resets included, writing its JSON."""

from __future__ import annotations

import importlib.util
import json
import subprocess
import sys
import tomllib

import pytest

from helpers import ROOT

PEER = ROOT / "benchmarks" / "peers" / "mjwarp_ppo.py"
CONFIG = ROOT / "configs" / "mjwarp_pickcube.toml"


def load_peer():
    spec = importlib.util.spec_from_file_location("mjwarp_ppo_peer", PEER)
    module = importlib.util.module_from_spec(spec)
    sys.modules[spec.name] = module  # its dataclass looks itself up there
    spec.loader.exec_module(module)
    return module


@pytest.mark.skipif(not CONFIG.exists(), reason="configs/mjwarp_pickcube.toml is not there")
def test_mjwarp_peer_defaults_are_ebrls_config_for_the_race():
    cfg = tomllib.loads(CONFIG.read_text())
    args = load_peer().parse_args([])
    chunk = cfg["policy"]["chunk"]
    assert args.env == cfg["env"]["id"]
    assert args.num_envs == cfg["sim"]["groups"] * cfg["sim"]["envs_per_group"]
    assert args.batch_size == cfg["train"]["batch_size"] * chunk  # env steps per update
    assert args.total_timesteps == cfg["run"]["iterations"] * cfg["train"]["batch_size"] * chunk
    assert [int(w) for w in args.hidden.split(",")] == cfg["policy"]["hidden"]
    assert args.init_log_std == cfg["policy"]["init_log_std"]
    assert args.normalize_obs == cfg["policy"]["normalize_obs"]
    assert (args.gamma, args.gae_lambda, args.clip_coef) == (cfg["algo"]["gamma"], cfg["algo"]["gae_lambda"],
                                                            cfg["algo"]["clip"])
    assert (args.update_epochs, args.num_minibatches) == (cfg["algo"]["epochs"], cfg["algo"]["minibatches"])
    assert args.learning_rate == cfg["train"]["lr"] and args.target_success == cfg["run"]["target_success"]
    assert args.seed == cfg["run"]["seed"]


def test_mjwarp_peer_runs_on_warp_cpu_and_writes_json(tmp_path):
    try:
        import mujoco_warp  # noqa: F401
        import warp  # noqa: F401
    except Exception as exc:  # noqa: BLE001  (an ImportError, or Warp failing to load its library)
        pytest.skip(f"MuJoCo Warp does not import here: {exc}")
    out = tmp_path / "peer.json"
    # 8 worlds x 52 steps x 2 updates: 104 steps of each world, past the 100-step limit, so every world ends an
    # episode (a truncation or a termination) and is reset in the middle of a rollout
    proc = subprocess.run([sys.executable, str(PEER), "--device", "cpu", "--num-envs", "8", "--num-steps", "52",
                           "--num-minibatches", "4", "--update-epochs", "2", "--total-timesteps", str(8 * 52 * 2),
                           "--max-seconds", "240", "--torch-threads", "1", "--seed", "3", "--json", str(out)],
                          cwd=ROOT, capture_output=True, text=True, timeout=300)
    assert proc.returncode == 0, proc.stdout[-2000:] + proc.stderr[-3000:]
    result = json.loads(out.read_text())
    summary = result["summary"]
    assert result["device"] == "cpu" and result["hyperparameters"]["action_chunk"] == 1
    assert summary["stop_reason"] == "total_timesteps", summary
    assert summary["env_steps"] == 8 * 52 * 2 and summary["updates"] == 2
    assert summary["episodes"] >= 8 and summary["env_steps_per_s"] > 0
    assert summary["target_reached"] is None  # 8 or so episodes: the 20-episode window is not full
    assert 0.0 <= summary["final_success_rate"] <= 1.0 and 0.0 <= summary["final_return"] <= 100.0
    curve = result["curve"]
    assert [p["updates"] for p in curve] == [1, 2] and [p["env_steps"] for p in curve] == [416, 832]
    assert curve[1]["success_rate"] is not None and curve[1]["episodes"] >= 8  # every world ended an episode
    assert "env steps/s" in proc.stdout and f"wrote {out}" in proc.stdout
