"""A portable policy: checkpoints carry their config, ``ebrl.load_policy`` rebuilds them and acts step by step."""

import dataclasses
import json
import os
import stat
import subprocess
import sys
from types import SimpleNamespace

import gymnasium as gym
import numpy as np
import pytest
import torch

import ebrl
from ebrl.algos import checkpoint
from ebrl.algos.learner import Learner
from ebrl.config import Config, PolicySection, dump_toml
from ebrl.envs import EnvSpec, ObsField, ObsLayout, describe
from ebrl.evaluate import run_episodes
from ebrl.policies import make_policy, save_checkpoint
from ebrl.policies.checkpoint import portable_metadata, read_metadata
from ebrl.policies.portable import PolicyFileError, resolve

CFG = Config()  # the default env: InvertedPendulum-v5, the quickstart's
INFO = describe(EnvSpec.from_config(CFG.env))
VISION = ObsLayout((ObsField("image", "image", (3, 16, 16)), ObsField("proprio", "vector", (4,))))


def policy_cfg(kind: str, **changes) -> PolicySection:
    return dataclasses.replace(PolicySection(kind=kind, chunk=4, hidden=[16], channels=[4], embed_dim=8,
                                             denoise_steps=3), **changes)


def fake_info(layout: ObsLayout, action_dim: int = 2, bound: float = 1.0):
    box = gym.spaces.Box(-bound, bound, (action_dim,), np.float32)
    return SimpleNamespace(obs_shape=(layout.size,), action_space=box, layout=layout, action_dim=action_dim)


def saved(tmp_path, kind: str = "mlp", info=INFO, name: str = "policy.safetensors", version: int = 3, seed: int = 0,
          **changes):
    torch.manual_seed(seed)
    cfg = policy_cfg(kind, **changes)
    model = make_policy(cfg, info.layout, info.action_dim)
    path = tmp_path / name
    save_checkpoint(model, str(path), {"version": str(version), **portable_metadata(cfg, CFG.env, info)})
    return model, path


def obs_batch(layout: ObsLayout, n: int = 3, seed: int = 0) -> np.ndarray:
    return np.random.default_rng(seed).uniform(0, 1, (n, layout.size)).astype(np.float32)


@pytest.mark.parametrize("kind,layout", [("mlp", INFO.layout), ("flow", INFO.layout), ("cnn", VISION),
                                         ("flow", VISION)])
def test_round_trip_rebuilds_the_policy_without_its_config(tmp_path, kind, layout):
    info = INFO if layout is INFO.layout else fake_info(layout)
    model, path = saved(tmp_path, kind, info, normalize_obs=True)
    with torch.no_grad():  # a normaliser with statistics: they must travel with the weights
        model.obs_norm.merge(model.obs_norm.sums(torch.randn(32, layout.size) * 3 + 1))
    save_checkpoint(model, str(path), read_metadata(str(path)))
    policy = ebrl.load_policy(path)
    assert (policy.kind, policy.chunk, policy.action_dim, policy.version) == (kind, 4, info.action_dim, 3)
    assert policy.layout == layout and policy.policy_config["normalize_obs"] is True
    obs = obs_batch(layout)
    np.testing.assert_array_equal(policy.model.obs_norm.mean.numpy(), model.obs_norm.mean.numpy())
    expected = model.predict_chunk(obs, deterministic=True)
    np.testing.assert_allclose(policy.predict_chunk(obs), np.clip(expected, -1 if layout is VISION else -3,
                                                                   1 if layout is VISION else 3), rtol=0, atol=1e-6)


def test_deterministic_means_the_gaussian_mean_and_the_flow_chain_from_zero_noise(tmp_path):
    obs = obs_batch(INFO.layout)
    mlp = ebrl.load_policy(saved(tmp_path, "mlp", name="mlp.safetensors")[1]).model
    mean = mlp.heads(mlp.flat(obs))[0].mean.reshape(3, 4, 1)
    np.testing.assert_allclose(mlp.predict_chunk(obs), mean.detach().numpy(), atol=1e-6)
    flow = ebrl.load_policy(saved(tmp_path, "flow", name="flow.safetensors")[1]).model
    with torch.no_grad():
        mu = flow.mean(flow.encoder(flow.flat(obs)), torch.zeros(3, 4))
    np.testing.assert_allclose(flow.predict_chunk(obs), mu.reshape(3, 4, 1).numpy(), atol=1e-6)


@pytest.mark.parametrize("kind", ["mlp", "flow"])
def test_actions_are_reproducible_deterministic_or_seeded(tmp_path, kind):
    _, path = saved(tmp_path, kind, init_log_std=0.0)
    obs = obs_batch(INFO.layout)
    a, b = ebrl.load_policy(path), ebrl.load_policy(path, seed=123)
    np.testing.assert_array_equal(a.predict_chunk(obs), b.predict_chunk(obs))  # deterministic: no randomness
    a.reset(seed=7)
    b.reset(seed=7)
    first = a.predict_chunk(obs, deterministic=False)
    np.testing.assert_array_equal(first, b.predict_chunk(obs, deterministic=False))
    assert not np.allclose(first, a.predict_chunk(obs, deterministic=False))  # the generator moved on
    assert not np.allclose(first, a.predict_chunk(obs))


def test_predict_hands_out_the_chunk_one_action_per_call(tmp_path):
    policy = ebrl.load_policy(saved(tmp_path, "mlp", init_log_std=0.0)[1])
    first, later = obs_batch(INFO.layout, 2, seed=1)
    chunk = policy.predict_chunk(first[None])[0]
    got = [policy.predict(first)[0]] + [policy.predict(later)[0] for _ in range(3)]  # the first obs's chunk
    np.testing.assert_array_equal(np.stack(got), chunk)
    assert policy.predict(later)[0].shape == (1,)  # spent: a new chunk, from the observation given now
    np.testing.assert_array_equal(policy._actions[0], policy.predict_chunk(later[None])[0])
    policy.reset()  # an episode boundary: the rest of the chunk is dropped
    np.testing.assert_array_equal(policy.predict(first)[0], chunk[0])
    policy.predict(later)
    action, state = policy.predict(first, episode_start=True)  # the same, Stable-Baselines3's way
    np.testing.assert_array_equal(action, chunk[0])
    assert state is None


def test_a_batch_of_envs_keeps_a_chunk_each_and_resets_one(tmp_path):
    policy = ebrl.load_policy(saved(tmp_path, "mlp")[1])
    obs = obs_batch(INFO.layout, 3)
    chunks = policy.predict_chunk(obs)
    np.testing.assert_array_equal(policy.predict(obs)[0], chunks[:, 0])
    policy.reset(1)
    other = obs_batch(INFO.layout, 3, seed=5)
    step, _ = policy.predict(other)
    np.testing.assert_array_equal(step[[0, 2]], chunks[[0, 2], 1])
    np.testing.assert_array_equal(step[1], policy.predict_chunk(other[1:2])[0, 0])
    step, _ = policy.predict(obs, episode_start=[False, False, True])  # env 2's episode starts: a new chunk
    np.testing.assert_array_equal(step[[0, 1]], np.stack([chunks[0, 2], policy._actions[1, 1]]))
    np.testing.assert_allclose(step[2], chunks[2, 0], rtol=1e-5)  # a batch of 1 here, of 3 there
    with pytest.raises(ValueError, match="takes"):
        policy.predict(np.zeros(5))


def test_actions_are_clipped_to_the_bounds(tmp_path):
    model, path = saved(tmp_path, "mlp")
    with torch.no_grad():
        model.actor[-1].bias.fill_(50.0)
    save_checkpoint(model, str(path), read_metadata(str(path)))
    policy = ebrl.load_policy(path)
    assert INFO.action_space.high[0] == 3.0
    assert policy.predict(obs_batch(INFO.layout, 1)[0])[0].tolist() == [3.0]
    assert (policy.predict_chunk(obs_batch(INFO.layout), deterministic=False) == 3.0).all()


def test_policy_files_are_group_readable(tmp_path):
    os.umask(0o022)
    _, path = saved(tmp_path)
    mode = stat.S_IMODE(os.stat(path).st_mode)
    assert mode == 0o644 and not [p for p in os.listdir(tmp_path) if p.endswith(".tmp")]


def test_an_old_checkpoint_needs_its_config_and_says_so(tmp_path):
    cfg = policy_cfg("mlp")
    model = make_policy(cfg, INFO.layout, INFO.action_dim)
    path = tmp_path / "old.safetensors"
    save_checkpoint(model, str(path), {"version": "5"})  # what EBRL wrote before portable metadata
    with pytest.raises(PolicyFileError, match="config='RUN_DIR/config.toml'"):
        ebrl.load_policy(path)
    run_cfg = dataclasses.replace(CFG, policy=cfg)
    (tmp_path / "config.toml").write_text(dump_toml(run_cfg))
    policy = ebrl.load_policy(path, config=tmp_path / "config.toml")
    obs = obs_batch(INFO.layout)
    np.testing.assert_allclose(policy.predict_chunk(obs), np.clip(model.predict_chunk(obs), -3, 3))
    assert policy.version == 5 and policy.env_config["id"] == CFG.env.id


def test_a_run_directory_gives_its_latest_policy_or_its_best(tmp_path):
    _, final = saved(tmp_path, version=20)
    model = make_policy(policy_cfg("mlp"), INFO.layout, INFO.action_dim)
    optimizer = torch.optim.Adam(model.parameters())
    meta = portable_metadata(policy_cfg("mlp"), CFG.env, INFO)
    checkpoint.save(tmp_path, model, optimizer, 30, {}, meta)  # a resumed run went on past policy.safetensors
    assert resolve(tmp_path) == tmp_path / "checkpoints" / "v00000030" / "policy.safetensors"
    assert ebrl.load_policy(tmp_path).version == 30
    assert resolve(tmp_path / "checkpoints" / "v00000030") == tmp_path / "checkpoints" / "v00000030" / "policy.safetensors"
    checkpoint.save(tmp_path, model, optimizer, 10, {}, meta)  # older than policy.safetensors
    assert resolve(tmp_path) == final
    with pytest.raises(PolicyFileError, match="no best.safetensors"):
        resolve(tmp_path, "best")
    saved(tmp_path, name="best.safetensors", version=15)
    assert ebrl.load_policy(tmp_path, which="best").version == 15
    with pytest.raises(PolicyFileError, match="no such file"):
        ebrl.load_policy(tmp_path / "absent")


def test_training_writes_portable_policies_and_checkpoints(tmp_path):
    cfg = dataclasses.replace(CFG, policy=policy_cfg("mlp"))
    telemetry = SimpleNamespace(count=lambda *a: None, publish_span=lambda *a: None)
    learner = Learner(cfg, INFO, 1, telemetry, str(tmp_path))
    learner.version = 1  # as after one update
    learner.arrays = {k: v.detach().numpy().copy() for k, v in learner.model.state_dict().items()}
    learner.save_checkpoint("r")
    learner.save_policy("r")
    for path in (tmp_path / "policy.safetensors", checkpoint.latest(tmp_path) / "policy.safetensors"):
        metadata = read_metadata(str(path))
        assert json.loads(metadata["policy"])["hidden"] == [16] and json.loads(metadata["env"])["id"] == CFG.env.id
        assert json.loads(metadata["action_high"]) == [3.0] and json.loads(metadata["obs_shape"]) == [4]
        assert ebrl.load_policy(path).version == 1


SCRIPT = """\
import sys, gymnasium as gym, ebrl
policy = ebrl.load_policy(sys.argv[1])
env = gym.make("InvertedPendulum-v5")
obs, _ = env.reset(seed=2_000_000_000)
total, done = 0.0, False
while not done:
    action, _ = policy.predict(obs)
    obs, reward, terminated, truncated, _ = env.step(action)
    total, done = total + reward, terminated or truncated
print(total)
"""


def test_a_ten_line_script_runs_the_policy_in_a_plain_gymnasium_loop(tmp_path):
    assert len(SCRIPT.splitlines()) == 10
    _, path = saved(tmp_path, "mlp", seed=4)
    (tmp_path / "play.py").write_text(SCRIPT)
    env = dict(os.environ, PYTHONPATH=os.pathsep.join([str(tmp_path.parent), *sys.path]))
    out = subprocess.run([sys.executable, str(tmp_path / "play.py"), str(path)], capture_output=True, text=True,
                         timeout=120, env=env)
    assert out.returncode == 0, out.stderr
    expected = run_episodes(ebrl.load_policy(path), 1).episodes[0].ret  # the same episode, through the library
    assert float(out.stdout.strip().splitlines()[-1]) == expected > 0
