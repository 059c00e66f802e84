"""Training checkpoints: a round trip restores policy, optimizer, random state and version; writes are atomic."""

import dataclasses
from types import SimpleNamespace

import numpy as np
import pytest
import torch

from ebrl.algos import checkpoint
from ebrl.algos.ppo import PPO
from ebrl.config import PolicySection
from ebrl.envs import ObsLayout
from ebrl.policies import make_policy, state_arrays

POLICY = PolicySection(kind="mlp", chunk=2, hidden=[8], init_log_std=-0.5, channels=[8], embed_dim=8,
                       denoise_steps=2, checkpoint="")
ALGO = SimpleNamespace(clip=0.2, epochs=1, minibatches=1, ent_coef=0.0, vf_coef=0.5, max_grad_norm=0.5)


def trained(seed=0, steps=3):
    torch.manual_seed(seed)
    model = make_policy(POLICY, ObsLayout.vector(3), 1)
    ppo = PPO(model, ALGO, lr=1e-2, seed=seed)
    for _ in range(steps):  # give Adam some state
        loss = model.evaluate(torch.randn(4, 3), torch.randn(4, 2, 1), torch.zeros(4, 0))[0].sum()
        ppo.optimizer.zero_grad()
        loss.backward()
        ppo.optimizer.step()
    return model, ppo


def test_round_trip_restores_everything(tmp_path):
    model, ppo = trained()
    torch.randperm(5, generator=ppo.generator)  # move the generator on
    path = checkpoint.save(tmp_path, model, ppo.optimizer, 7, {"ppo": ppo.generator})
    assert checkpoint.latest(tmp_path) == path and path.name == "v00000007"
    expected_perm = torch.randperm(10, generator=ppo.generator)
    expected_global = torch.rand(3)
    expected_opt = {k: v.clone() for k, v in ppo.optimizer.state_dict()["state"][0].items()}

    fresh, fresh_ppo = trained(seed=1, steps=1)
    restored = checkpoint.restore(path, fresh, fresh_ppo.optimizer, {"ppo": fresh_ppo.generator})
    assert restored.version == 7
    for name, value in state_arrays(model).items():
        np.testing.assert_array_equal(state_arrays(fresh)[name], value)
    for key, value in fresh_ppo.optimizer.state_dict()["state"][0].items():
        torch.testing.assert_close(value, expected_opt[key])
    assert torch.equal(torch.randperm(10, generator=fresh_ppo.generator), expected_perm)
    assert torch.equal(torch.rand(3), expected_global)


def test_latest_always_names_a_complete_checkpoint_and_old_ones_go(tmp_path):
    model, ppo = trained()
    for version in (10, 20, 30):
        checkpoint.save(tmp_path, model, ppo.optimizer, version, {})
    root = checkpoint.checkpoint_dir(tmp_path)
    assert sorted(p.name for p in root.iterdir() if p.is_dir()) == ["v00000020", "v00000030"]
    (root / "v00000040.tmp").mkdir()  # a crash in the middle of writing v40
    (root / "v00000040.tmp" / "policy.safetensors").write_bytes(b"half")
    assert checkpoint.latest(tmp_path).name == "v00000030"
    assert checkpoint.latest(tmp_path / "nothing") is None


def test_a_checkpoint_of_another_policy_is_refused(tmp_path):
    model, ppo = trained()
    path = checkpoint.save(tmp_path, model, ppo.optimizer, 1, {})
    other = make_policy(dataclasses.replace(POLICY, hidden=[16]), ObsLayout.vector(3), 1)
    with pytest.raises(ValueError, match="shape"):
        checkpoint.restore(path, other, PPO(other, ALGO, lr=1e-2).optimizer, {})
