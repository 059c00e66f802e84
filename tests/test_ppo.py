"""PPO pieces: GAE by hand, bootstrapping rules, log-prob consistency between gen and train, learning signal."""

import numpy as np
import torch
from types import SimpleNamespace

from ebrl.config import PolicySection
from ebrl.envs.obs import ObsLayout
from ebrl.algos.ppo import PPO, build_batch, gae
from ebrl.envs.worker import ChunkResult
from ebrl.policies import load_arrays, make_policy, state_arrays
from ebrl.sched.rollout import SegmentBuilder

ALGO = SimpleNamespace(gamma=0.9, gae_lambda=0.5, clip=0.2, epochs=4, minibatches=2, ent_coef=0.0, vf_coef=0.5,
                       max_grad_norm=0.5)
POLICY = PolicySection(kind="mlp", chunk=3, hidden=[16], init_log_std=-0.5, checkpoint="")


def test_gae_matches_hand_computation():
    r = np.array([1.0, 0.0, 2.0], np.float32)
    v = np.array([0.5, 1.0, 1.5], np.float32)
    d = np.array([0.9, 0.81, 0.9], np.float32)  # gamma**steps, second chunk ran 2 steps
    adv, ret = gae(r, v, d, last_value=2.0, lam=0.5)
    d2 = 2.0 + 0.9 * 2.0 - 1.5
    d1 = 0.0 + 0.81 * 1.5 - 1.0
    d0 = 1.0 + 0.9 * 1.0 - 0.5
    a2 = d2
    a1 = d1 + 0.81 * 0.5 * a2
    a0 = d0 + 0.9 * 0.5 * a1
    np.testing.assert_allclose(adv, [a0, a1, a2], rtol=1e-6)
    np.testing.assert_allclose(ret, adv + v, rtol=1e-6)


def result(steps=3, reward=1.0, terminated=False, truncated=False, ep=None):
    o = np.zeros(4, np.float32)
    return ChunkResult(reward, steps, terminated, truncated, o + 1, o, ep, 10 if ep is not None else None)


def test_segments_end_on_termination_truncation_and_length():
    b = SegmentBuilder(group=0, env_id=5, length=3)
    obs, act = np.zeros(4, np.float32), np.zeros((3, 1), np.float32)
    assert b.add(obs, act, np.zeros(0, np.float32), -1.0, 0.0, 0, result()) is None
    seg = b.add(obs, act, np.zeros(0, np.float32), -1.0, 0.0, 1, result(steps=2, terminated=True, ep=7.0))
    assert seg.end == "terminated" and list(seg.versions) == [0, 1] and list(seg.steps) == [3, 2]
    assert seg.episode_returns == [7.0] and len(b) == 0
    np.testing.assert_array_equal(seg.last_obs, np.ones(4))  # final obs, not the reset one
    for _ in range(2):
        assert b.add(obs, act, np.zeros(0, np.float32), -1.0, 0.0, 2, result()) is None
    seg = b.add(obs, act, np.zeros(0, np.float32), -1.0, 0.0, 2, result())
    assert seg.end == "cut" and len(seg.obs) == 3
    np.testing.assert_array_equal(seg.last_obs, np.zeros(4))  # next obs to bootstrap from
    seg = b.add(obs, act, np.zeros(0, np.float32), -1.0, 0.0, 3, result(truncated=True, ep=30.0))
    assert seg.end == "truncated" and len(seg.obs) == 1


def test_terminated_segments_do_not_bootstrap():
    torch.manual_seed(0)
    model = make_policy(POLICY, ObsLayout.vector(4), 1)
    b = SegmentBuilder(0, 0, 8)
    obs, act = np.ones(4, np.float32), np.zeros((3, 1), np.float32)
    term = b.add(obs, act, np.zeros(0, np.float32), 0.0, 0.0, 0, result(reward=1.0, terminated=True, ep=1.0))
    b2 = SegmentBuilder(0, 1, 1)
    cut = b2.add(obs, act, np.zeros(0, np.float32), 0.0, 0.0, 0, result(reward=1.0))
    batch = build_batch([term, cut], model, gamma=0.9, lam=1.0)
    last_v = model.value(torch.as_tensor(cut.last_obs[None])).item()
    np.testing.assert_allclose(batch.returns.numpy(), [1.0, 1.0 + 0.9 ** 3 * last_v], rtol=1e-5)


def test_log_prob_is_the_same_in_gen_and_train():
    torch.manual_seed(1)
    gen_model, train_model = make_policy(POLICY, ObsLayout.vector(4), 2), make_policy(POLICY, ObsLayout.vector(4), 2)
    load_arrays(gen_model, state_arrays(train_model))  # what a Weights message carries
    obs = np.random.default_rng(0).normal(size=(5, 4)).astype(np.float32)
    actions, logprobs, values, latents = gen_model.act(obs)
    assert actions.shape == (5, 3, 2) and latents.shape == (5, 0)
    lp, _, v = train_model.evaluate(torch.as_tensor(obs), torch.as_tensor(actions), torch.as_tensor(latents))
    np.testing.assert_allclose(lp.detach().numpy(), logprobs, rtol=1e-5, atol=1e-5)
    np.testing.assert_allclose(v.detach().numpy(), values, rtol=1e-5, atol=1e-5)


def test_load_arrays_rejects_mismatched_weights():
    model = make_policy(POLICY, ObsLayout.vector(4), 2)
    other = make_policy(SimpleNamespace(**{**vars(POLICY), "hidden": [8]}), ObsLayout.vector(4), 2)
    try:
        load_arrays(model, state_arrays(other))
    except ValueError as exc:
        assert "shape" in str(exc)
    else:
        raise AssertionError("mismatched weights were accepted")


def test_ppo_update_moves_probability_towards_advantaged_actions():
    torch.manual_seed(2)
    model = make_policy(POLICY, ObsLayout.vector(4), 1)
    obs = np.zeros((64, 4), np.float32)
    actions, logprobs, values, latents = model.act(obs)
    good = actions.reshape(64, -1).mean(1) > 0  # reward chunks whose mean action is positive
    b = SegmentBuilder(0, 0, 64)
    seg = None
    for i in range(64):
        seg = b.add(obs[i], actions[i], latents[i], float(logprobs[i]), float(values[i]), 0,
                    result(reward=float(good[i]), terminated=(i == 63), ep=1.0 if i == 63 else None))
    batch = build_batch([seg], model, gamma=0.0, lam=0.0)
    before = model.dist(torch.zeros(1, 4)).mean.mean().item()
    PPO(model, ALGO, lr=1e-2).update(batch)
    after = model.dist(torch.zeros(1, 4)).mean.mean().item()
    assert after > before
