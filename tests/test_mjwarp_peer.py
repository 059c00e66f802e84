"""The MuJoCo Warp peer (benchmarks/peers/mjwarp_ppo.py): its defaults are EBRL's config for the race, its update is
EBRL's PPO update, and it runs end to end on Warp's CPU device, partial resets included, writing its JSON."""

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


def test_the_peers_update_is_ebrls_ppo_update():
    """Given the same weights, data and minibatch orders, one update of the peer (CleanRL's loop) and one of EBRL's
    PPO leave the same weights: where the two sides learn at different speeds, the difference is in the data they
    collect, not in the update."""
    import types

    import numpy as np
    import torch

    from ebrl.algos.ppo import PPO, Batch
    from ebrl.envs.obs import ObsField, ObsLayout
    from ebrl.policies.mlp import ChunkGaussianMLP

    peer = load_peer()
    torch.manual_seed(0)
    dim, act, n, hidden = 12, 4, 256, [32, 32]
    model = ChunkGaussianMLP(ObsLayout((ObsField("state", "vector", (dim,)),)), act, 1, hidden, -0.5)
    agent = peer.Agent(dim, act, hidden, -0.5)
    weights = {k: v.clone() for k, v in model.state_dict().items()}
    for prefix, net in (("actor.", agent.actor_mean), ("critic.", agent.critic)):
        net.load_state_dict({k.removeprefix(prefix): v for k, v in weights.items() if k.startswith(prefix)})
    agent.actor_logstd.data.copy_(weights["log_std"].view(1, -1))
    obs = torch.randn(n, dim)
    with torch.no_grad():
        actions, logp, values, _ = model.sample(obs)
    actions = actions.reshape(n, act)
    advantages = torch.randn(n) * 2 + 0.3
    returns = values + advantages
    # a large step, so that the ratios leave the clip range in the second epoch and the clipping is compared too
    args = peer.parse_args(["--update-epochs", "2", "--num-minibatches", "4", "--learning-rate", "0.01"])
    cfg = types.SimpleNamespace(epochs=2, minibatches=4, clip=args.clip_coef, ent_coef=args.ent_coef,
                                vf_coef=args.vf_coef, max_grad_norm=args.max_grad_norm, decoupled=True,
                                prox_logp="recompute", behave_weight_cap=5.0)
    ppo = PPO(model, cfg, args.learning_rate, seed=7)
    generator = torch.Generator().manual_seed(7)  # EBRL's permutations, handed to the peer
    orders = [torch.randperm(n, generator=generator) for _ in range(2)]
    optimizer = torch.optim.Adam(agent.parameters(), lr=args.learning_rate, eps=1e-5)
    peer.ppo_update(agent, optimizer, args, obs, actions, logp, advantages, returns, orders)
    stats = ppo.update(Batch(obs=obs, actions=actions.reshape(n, 1, act), latents=torch.zeros(n, 0), logprobs=logp,
                             advantages=advantages, returns=returns, values=values, versions=np.zeros(n, np.int64)))
    after = model.state_dict()
    moved = max((after[k] - weights[k]).abs().max().item() for k in after if k.startswith("actor."))
    assert moved > 1e-4 and stats["clipfrac"] > 0  # the update did something, the clip too
    for prefix, net in (("actor.", agent.actor_mean), ("critic.", agent.critic)):
        for key, value in net.state_dict().items():
            torch.testing.assert_close(after[prefix + key], value, atol=1e-6, rtol=1e-5)
    torch.testing.assert_close(after["log_std"], agent.actor_logstd.detach().view(-1), atol=1e-6, rtol=1e-5)
