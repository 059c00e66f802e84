"""PPO pieces: GAE by hand, bootstrapping rules, log-prob consistency between gen and train, learning signal."""

import dataclasses

import numpy as np
import pytest
import torch
from types import SimpleNamespace

from ebrl.config import PolicySection
from ebrl.envs.obs import ObsLayout
from ebrl.algos.ppo import PPO, BadBatch, Batch, build_batch, gae, gae_segments
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


def test_gae_of_many_segments_at_once_is_each_segments_gae_bit_for_bit():
    """The backward recursion written out for one segment in plain Python floats (the definition), against
    ``gae_segments`` over ragged segments laid one after another: the same float64 operations, so equal."""
    def by_hand(r, v, d, last, lam):
        adv, next_value, acc = [0.0] * len(r), float(last), 0.0
        for t in reversed(range(len(r))):
            acc = (float(r[t]) + float(d[t]) * next_value - float(v[t])) + float(d[t]) * lam * acc
            adv[t], next_value = acc, float(v[t])
        return np.array(adv)

    rng = np.random.default_rng(7)
    lengths = np.array([3, 1, 8, 8, 5, 1, 2, 8, 7])
    n = int(lengths.sum())
    r, v = rng.normal(size=n).astype(np.float32), rng.normal(size=n).astype(np.float32)
    d, last = 0.97 ** rng.integers(1, 5, n).astype(np.float64), rng.normal(size=len(lengths)).astype(np.float32)
    adv, ret = gae_segments(r, v, d, lengths, last, lam=0.95)
    starts = np.cumsum(lengths) - lengths
    for s, (a, length) in enumerate(zip(starts, lengths)):
        part = slice(a, a + length)
        expected = by_hand(r[part], v[part], d[part], last[s], 0.95)
        assert np.array_equal(adv[part], expected), s
        assert np.array_equal(ret[part], expected + v[part].astype(np.float64)), s
        assert all(np.array_equal(x, y) for x, y in zip(gae(r[part], v[part], d[part], float(last[s]), 0.95),
                                                         (adv[part], ret[part])))


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


# --- the formulas of the off-policy path, pinned (issue: learning parity) ---


def test_decoupled_policy_loss_matches_hand_computation():
    from ebrl.algos.ppo import policy_loss

    logp = torch.log(torch.tensor([1.1, 0.7, 1.5, 1.0]))  # pi_theta, relative to pi_prox = 1 below
    prox = torch.zeros(4)
    behave = torch.log(torch.tensor([0.5, 2.0, 1.0, 1 / 8]))  # w = pi_prox / pi_behave = 2, 0.5, 1, 8 -> cap 5
    adv = torch.tensor([1.0, -1.0, 2.0, -0.5])
    loss, w, r = policy_loss(logp, prox, behave, adv, clip=0.2, cap=5.0)
    torch.testing.assert_close(w, torch.tensor([2.0, 0.5, 1.0, 5.0]))
    torch.testing.assert_close(r, torch.tensor([1.1, 0.7, 1.5, 1.0]))
    # per decision: w * max(-A r, -A clip(r, 0.8, 1.2))
    terms = [2.0 * max(-1.1, -1.1), 0.5 * max(0.7, 0.8), 1.0 * max(-3.0, -2.4), 5.0 * max(0.5, 0.5)]
    assert loss.item() == pytest.approx(sum(terms) / 4, rel=1e-6)


def test_decoupled_weight_carries_no_gradient_and_is_one_on_policy():
    from ebrl.algos.ppo import policy_loss

    logp = torch.tensor([-0.3, -1.2], requires_grad=True)
    prox = logp.detach() + torch.tensor([0.2, -0.4])  # interpolation makes pi_prox from pi_theta, detached
    loss, w, _ = policy_loss(logp, prox, logp.detach(), torch.tensor([1.0, 1.0]), 0.2, 5.0)
    assert not w.requires_grad
    loss.backward()
    assert logp.grad is not None
    _, w_on, r_on = policy_loss(logp.detach(), logp.detach(), logp.detach(), torch.ones(2), 0.2, 5.0)
    torch.testing.assert_close(w_on, torch.ones(2))
    torch.testing.assert_close(r_on, torch.ones(2))


def stale_segment(model, T=6, end="cut"):
    """A segment acted by an older critic: its stored values are not what ``model`` says now."""
    rng = np.random.default_rng(3)
    obs = rng.normal(size=(T, 4)).astype(np.float32)
    from ebrl.messages import TrajectorySegment

    return TrajectorySegment(
        group=0, env_id=0, episode=0, obs=obs, actions=np.zeros((T, 3, 1), np.float32),
        latents=np.zeros((T, 0), np.float32), logprobs=np.zeros(T, np.float32),
        values=rng.normal(size=T).astype(np.float32), rewards=rng.normal(size=T).astype(np.float32),
        steps=np.full(T, 3, np.int32), versions=np.zeros(T, np.int64), end=end,
        last_obs=rng.normal(size=4).astype(np.float32), episode_returns=[], episode_lengths=[])


def test_gae_on_a_stale_segment_takes_every_value_from_the_current_critic():
    torch.manual_seed(4)
    model = make_policy(POLICY, ObsLayout.vector(4), 1)
    seg = stale_segment(model)
    gamma, lam = 0.9, 0.8
    with torch.no_grad():
        v_now = model.value(torch.as_tensor(seg.obs)).numpy()
        v_last = model.value(torch.as_tensor(seg.last_obs[None])).item()
    disc = gamma ** seg.steps.astype(np.float64)
    batch = build_batch([seg], model, gamma, lam)  # values = "current", the default
    adv, ret = gae(seg.rewards, v_now, disc, v_last, lam)
    np.testing.assert_allclose(batch.advantages.numpy(), adv, rtol=1e-5, atol=1e-6)
    np.testing.assert_allclose(batch.returns.numpy(), ret, rtol=1e-5, atol=1e-6)
    np.testing.assert_allclose(batch.values.numpy(), v_now, rtol=1e-5, atol=1e-6)
    assert batch.diagnostics["value_drift"] == pytest.approx(float(np.sqrt(np.mean((v_now - seg.values) ** 2))),
                                                            rel=1e-5)
    # "behaviour": the acting critic's values inside the segment, the bootstrap from the current critic
    old = build_batch([seg], model, gamma, lam, values="behaviour")
    adv_b, _ = gae(seg.rewards, seg.values, disc, v_last, lam)
    np.testing.assert_allclose(old.advantages.numpy(), adv_b, rtol=1e-5, atol=1e-6)
    assert not np.allclose(old.advantages.numpy(), batch.advantages.numpy())
    # a terminated segment bootstraps from nothing, whichever critic
    term = stale_segment(model, end="terminated")
    adv_t, _ = gae(term.rewards, v_now, disc, 0.0, lam)
    np.testing.assert_allclose(build_batch([term], model, gamma, lam).advantages.numpy(), adv_t, rtol=1e-5,
                               atol=1e-6)


def test_gae_values_are_the_same_either_way_on_policy():
    torch.manual_seed(5)
    model = make_policy(POLICY, ObsLayout.vector(4), 1)
    seg = stale_segment(model)
    with torch.no_grad():
        seg.values[:] = model.value(torch.as_tensor(seg.obs)).numpy()  # acted by this very critic
    a = build_batch([seg], model, 0.99, 0.95)
    b = build_batch([seg], model, 0.99, 0.95, values="behaviour")
    torch.testing.assert_close(a.advantages, b.advantages)
    assert a.diagnostics["value_drift"] == pytest.approx(0.0, abs=1e-6)


def test_update_reports_how_far_the_behaviour_policy_is():
    torch.manual_seed(6)
    model = make_policy(POLICY, ObsLayout.vector(4), 1)
    seg = stale_segment(model, end="terminated")
    actions = torch.randn(len(seg.obs), 3, 1)
    with torch.no_grad():
        logp = model.evaluate(torch.as_tensor(seg.obs), actions, torch.zeros(len(seg.obs), 0))[0].numpy()
    algo = SimpleNamespace(**vars(ALGO), decoupled=True, prox_logp="recompute", behave_weight_cap=5.0)
    for shift, kl, capped in ((0.0, 0.0, 0.0), (-2.0, np.exp(2.0) - 1 - 2.0, 1.0)):  # w = 1, then e^2 > cap
        behaved = seg.__class__(**{**seg.__dict__, "actions": actions.numpy(),
                                   "logprobs": (logp + shift).astype(np.float32)})
        stats = PPO(model, algo, lr=0.0).update(build_batch([behaved], model, 0.9, 0.9))
        assert stats["behave_kl"] == pytest.approx(kl, rel=1e-4, abs=1e-5)
        assert stats["behave_weight_capped"] == capped
        assert stats["behave_weight_mean"] == pytest.approx(min(np.exp(-shift), 5.0), rel=1e-4)
        assert {"value_drift", "explained_variance", "adv_mean", "adv_std"} <= set(stats)


# --- no bad step (issue 34): what cannot be learned from is dropped and counted, the weights stay finite ---


def test_gae_runs_in_float64_and_a_segment_whose_returns_overflow_is_left_out():
    r = np.array([3.0e38, 3.0e38], np.float32)  # each finite in float32; their sum is not
    adv, ret = gae(r, np.zeros(2, np.float32), np.ones(2), last_value=0.0, lam=1.0)
    assert adv.dtype == np.float64 and np.isfinite(ret).all() and ret[0] == pytest.approx(6.0e38)
    torch.manual_seed(0)
    model = make_policy(POLICY, ObsLayout.vector(4), 1)
    good, bad = stale_segment(model, end="terminated"), stale_segment(model, end="terminated")
    bad = dataclasses.replace(bad, rewards=np.full_like(bad.rewards, 3.0e38))
    batch = build_batch([good, bad], model, gamma=0.99, lam=0.95)
    assert len(batch) == len(good.obs) and batch.dropped == len(bad.obs)
    assert torch.isfinite(batch.returns).all()
    with pytest.raises(BadBatch) as caught:
        build_batch([bad], model, gamma=0.99, lam=0.95)
    assert caught.value.dropped == len(bad.obs)


def test_an_update_skips_a_step_that_is_not_finite_drops_its_data_and_keeps_the_weights_finite():
    torch.manual_seed(3)
    model = make_policy(POLICY, ObsLayout.vector(4), 1)
    n = 64
    obs = np.random.default_rng(0).normal(size=(n, 4)).astype(np.float32)
    actions, logprobs, values, latents = model.act(obs)
    returns = torch.randn(n)
    returns[5] = 3.0e38  # finite, but its squared error in the value loss is not
    batch = Batch(obs=torch.as_tensor(obs), actions=torch.as_tensor(actions), latents=torch.as_tensor(latents),
                  logprobs=torch.as_tensor(logprobs), advantages=torch.randn(n), returns=returns,
                  values=torch.as_tensor(values), versions=np.zeros(n, np.int64))
    before = state_arrays(model)
    out = PPO(model, ALGO, lr=1e-2).update(batch)
    assert out["steps_skipped"] == 1 and out["decisions_dropped"] == 1  # decision 5 only, then never again
    after = state_arrays(model)
    assert all(np.isfinite(a).all() for a in after.values())
    assert any(not np.array_equal(before[k], after[k]) for k in before)  # the other steps were taken
    assert all(np.isfinite(v) for k, v in out.items())


def skip_batch(model, n=64):
    """A batch whose decision 5 has a finite return whose squared error is not (tests below)."""
    obs = np.random.default_rng(0).normal(size=(n, 4)).astype(np.float32)
    actions, logprobs, values, latents = model.act(obs)
    returns = torch.randn(n, generator=torch.Generator().manual_seed(1))
    returns[5] = 3.0e38
    return Batch(obs=torch.as_tensor(obs), actions=torch.as_tensor(actions), latents=torch.as_tensor(latents),
                 logprobs=torch.as_tensor(logprobs), advantages=torch.randn(n, generator=torch.Generator().manual_seed(2)),
                 returns=returns, values=torch.as_tensor(values), versions=np.zeros(n, np.int64))


def test_a_fused_adam_skips_on_the_device_as_the_host_checked_path_does():
    """The fused Adam skips a bad step through ``found_inf`` (no read back to the host); an unfused one (a
    checkpoint of an older run restores ``fused = None``) is checked on the host: the same steps skipped, the
    same data dropped, the same numbers and weights."""
    from ebrl.algos.ppo import skips_on_device

    outs, weights = [], []
    for fused in (True, False):
        torch.manual_seed(3)
        model = make_policy(POLICY, ObsLayout.vector(4), 1)
        ppo = PPO(model, ALGO, lr=1e-2)
        if not fused:
            ppo.optimizer = torch.optim.Adam(model.parameters(), lr=1e-2, eps=1e-5)
        assert skips_on_device(ppo.optimizer) == fused
        outs.append(ppo.update(skip_batch(model)))
        weights.append(state_arrays(model))
    assert outs[0]["steps_skipped"] == outs[1]["steps_skipped"] == 1
    assert outs[0]["decisions_dropped"] == outs[1]["decisions_dropped"] == 1
    assert outs[0].keys() == outs[1].keys()
    for k in outs[0]:
        assert outs[0][k] == pytest.approx(outs[1][k], rel=1e-4, abs=1e-6), k
    for k in weights[0]:
        np.testing.assert_allclose(weights[0][k], weights[1][k], rtol=1e-4, atol=1e-6)


@pytest.mark.parametrize("decoupled, prox_logp", [(False, "recompute"), (True, "recompute"), (True, "interpolate")])
def test_the_host_reads_the_device_once_per_epoch_not_once_per_minibatch(monkeypatch, decoupled, prox_logp):
    """No host synchronisation in the inner loop (issue 35): the reads of a tensor's value by the host (what
    waits for a GPU) do not grow with the number of minibatches -- the statistics add up on the device and the
    bad-step verdicts are read once per epoch."""
    reads = {"n": 0}
    for name in ("item", "tolist", "cpu", "numpy", "__bool__", "__float__", "__int__"):
        original = getattr(torch.Tensor, name)

        def counted(self, *args, _original=original, **kwargs):
            reads["n"] += 1
            return _original(self, *args, **kwargs)

        monkeypatch.setattr(torch.Tensor, name, counted)

    def reads_for(minibatches: int) -> int:
        torch.manual_seed(3)
        model = make_policy(POLICY, ObsLayout.vector(4), 1)
        algo = SimpleNamespace(**{**vars(ALGO), "minibatches": minibatches, "decoupled": decoupled,
                                  "prox_logp": prox_logp, "behave_weight_cap": 5.0})
        batch = skip_batch(model)
        ppo = PPO(model, algo, lr=1e-3)
        ppo.prepare()
        reads["n"] = 0
        ppo.update(dataclasses.replace(batch, returns=torch.randn(len(batch))))
        return reads["n"]

    few, many = reads_for(2), reads_for(16)
    assert few == many and few <= 2 * ALGO.epochs + 6, (few, many)  # 2 per epoch; the batch's numbers; the end


@pytest.mark.gpu
@pytest.mark.skipif(not torch.cuda.is_available(), reason="needs a CUDA device (benchmarks/gpu/check.sh runs it on a "
                                                           "GPU machine)")
@pytest.mark.parametrize("dtype", ["float32", "bfloat16"])
def test_on_a_gpu_an_update_waits_for_the_device_once_per_epoch_and_skips_a_bad_step_there(dtype):
    """On CUDA, under torch's synchronisation debugging (each wait of the host for the device warns): the waits
    do not grow with the minibatches, and the bad step is skipped by the fused Adam with the weights finite."""
    import warnings

    from ebrl import devices

    def update(minibatches: int) -> tuple[int, dict[str, float]]:
        torch.manual_seed(3)
        model = make_policy(POLICY, ObsLayout.vector(4), 1).cuda()
        batch = skip_batch(model).to(torch.device("cuda"))
        ppo = PPO(model, SimpleNamespace(**{**vars(ALGO), "minibatches": minibatches}), lr=1e-2)
        ppo.prepare()
        ppo.update(dataclasses.replace(batch, returns=torch.randn(len(batch), device="cuda")))  # warm-up
        torch.cuda.synchronize()
        with warnings.catch_warnings(record=True) as caught, devices.autocast(torch.device("cuda"), dtype):
            warnings.simplefilter("always")
            torch.cuda.set_sync_debug_mode("warn")
            try:
                out = ppo.update(batch)
            finally:
                torch.cuda.set_sync_debug_mode("default")
        assert all(np.isfinite(a).all() for a in state_arrays(model).values())
        return sum("synchroniz" in str(w.message) for w in caught), out

    (few, out), (many, _) = update(2), update(16)
    assert out["steps_skipped"] == 1 and out["decisions_dropped"] == 1
    # A wait per minibatch would add 14 per epoch from 2 to 16 minibatches; the H200 read (11, 10): which minibatch
    # holds the bad decision moves a wait or two, so "does not grow" is within 2, not equal
    assert abs(few - many) <= 2 and max(few, many) <= 2 * ALGO.epochs + 8, (few, many)
