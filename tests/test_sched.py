"""Mode presets and overrides, the generation gate, staleness trimming, the decoupled PPO loss."""

import dataclasses

import numpy as np
import pytest
import torch
from types import SimpleNamespace

from ebrl.config import PolicySection
from ebrl.envs.obs import ObsLayout
from ebrl import config
from ebrl.algos.ppo import PPO, build_batch
from ebrl.messages import TrajectorySegment
from ebrl.policies import make_policy
from ebrl.sched.modes import resolve
from ebrl.algos.staleness import fresh_suffix, split


def cfg(**sections):
    return config.from_dict({"sim": {"groups": 2, "envs_per_group": 4}, "train": {"batch_size": 64}, **sections})


@pytest.mark.parametrize("mode, groups, stepping, rebinding, staleness", [
    ("ebrl", 2, "async", True, 2),
    ("colocated", 1, "batch", False, 0),
    ("hybrid", 2, "batch", False, 0),
    ("async", 1, "batch", False, 2),
])
def test_mode_presets(mode, groups, stepping, rebinding, staleness):
    s = resolve(cfg(run={"mode": mode}, algo={"max_staleness": 2}), cores=[0, 1, 2, 3])
    assert (s.groups, s.stepping, s.core_rebinding, s.max_staleness) == (groups, stepping, rebinding, staleness)
    assert s.groups * s.envs_per_group == 8 and s.rollout_length == 8
    if mode == "async":  # rollout and training on disjoint cores
        assert s.sim_cores == s.gen_cores == [0, 1] and s.train_cores == [2, 3]
    else:
        assert s.sim_cores == [0, 1, 2, 3] and s.train_cores == []


def test_ablation_switches_override_the_mode():
    s = resolve(cfg(sim={"groups": 2, "envs_per_group": 4, "core_rebinding": False, "group_pipeline": False},
                    train={"batch_size": 64, "overlap": False}), cores=[0, 1])
    assert (s.core_rebinding, s.groups, s.max_staleness, s.stepping) == (False, 1, 0, "async")
    assert not resolve(cfg(sim={"groups": 2, "envs_per_group": 4, "stepping": "batch"}), cores=[0]).core_rebinding


@pytest.mark.parametrize("value, pool, auto", [(None, True, True), ("auto", True, True), (True, True, False),
                                                (False, False, False)])
def test_core_rebinding_is_measured_by_default(value, pool, auto):
    sim = {"groups": 2, "envs_per_group": 4} | ({} if value is None else {"core_rebinding": value})
    s = resolve(cfg(sim=sim), cores=[0, 1])
    assert (s.core_rebinding, s.rebinding_auto) == (pool, auto)


def test_generation_gate_follows_iterations():
    s = resolve(cfg(algo={"max_staleness": 1}), cores=[0])  # 8 decisions per env per iteration
    assert [s.iteration_of(q) for q in (0, 7, 8, 15, 16)] == [0, 0, 1, 1, 2]
    assert s.min_version(0) == -1 and s.min_version(8) == 0 and s.min_version(16) == 1
    sync = resolve(cfg(train={"batch_size": 64, "overlap": False}), cores=[0])
    assert sync.min_version(8) == 1  # iteration 1 waits for the weights of update 0


def test_batch_size_must_divide_over_envs():
    with pytest.raises(config.ConfigError, match="train.batch_size = 60"):
        cfg(train={"batch_size": 60})


def segment(versions, T=None):
    T = len(versions)
    return TrajectorySegment(
        group=0, env_id=0, episode=0, obs=np.arange(T * 4, dtype=np.float32).reshape(T, 4),
        actions=np.zeros((T, 2, 1), np.float32), latents=np.zeros((T, 0), np.float32), logprobs=np.zeros(T, np.float32), values=np.zeros(T, np.float32),
        rewards=np.arange(T, dtype=np.float32), steps=np.full(T, 2, np.int32), versions=np.asarray(versions, np.int64),
        end="cut", last_obs=np.zeros(4, np.float32), episode_returns=[], episode_lengths=[])


def test_fresh_suffix_cuts_the_stale_prefix():
    seg = segment([3, 3, 4, 5, 5])
    same, dropped = fresh_suffix(seg, version=5, max_staleness=2)
    assert same is seg and dropped == 0
    cut, dropped = fresh_suffix(seg, version=6, max_staleness=1)
    assert dropped == 3 and list(cut.versions) == [5, 5] and list(cut.rewards) == [3.0, 4.0]
    assert cut.obs.shape == (2, 4) and cut.end == "cut"
    assert fresh_suffix(seg, version=9, max_staleness=1) == (None, 5)


def test_split_cuts_a_segment_that_bootstraps_from_the_rest():
    seg = dataclasses.replace(segment([0, 0, 1, 1, 1]), end="terminated", episode_returns=[7.0],
                              episode_lengths=[10], episode_successes=[True])
    first, rest = split(seg, 2)
    assert list(first.rewards) == [0.0, 1.0] and first.end == "cut" and first.episode_returns == []
    np.testing.assert_array_equal(first.last_obs, seg.obs[2])  # the bootstrap: where the rest starts
    assert list(rest.rewards) == [2.0, 3.0, 4.0] and rest.end == "terminated" and rest.episode_returns == [7.0]
    np.testing.assert_array_equal(np.concatenate([first.obs, rest.obs]), seg.obs)
    first.check(), rest.check()


def test_every_batch_is_exactly_batch_size_so_updates_keep_pace_with_the_iterations():
    """Segments cut at episode ends (5 and 3 decisions) do not line up with batches of 4: each batch takes 4
    decisions, the segment it ends in split, so the k-th update is ready once 4k decisions arrived. Taken
    whole, the first batch took 5 and the second waited for 9 decisions in all (the updates fell behind)."""
    from ebrl.algos.ppo import SegmentCollector
    c = SegmentCollector(SimpleNamespace(), max_pending=100, max_staleness=1, count=lambda *a: None)
    c.add(segment([0] * 5))
    first = c.take(version=0, batch_size=4)
    assert [len(s.obs) for s in first] == [4] and c.ready_steps == 1
    c.add(segment([0] * 3))
    assert c.ready_steps == 4  # the second batch is ready at 8 decisions, as the iterations are
    second = c.take(version=0, batch_size=4)
    assert [len(s.obs) for s in second] == [1, 3] and c.ready_steps == 0
    assert list(second[0].rewards) == [4.0]  # the first segment's last decision, in order


ALGO = dict(gamma=0.9, gae_lambda=0.9, clip=0.2, epochs=2, minibatches=2, ent_coef=0.0, vf_coef=0.5,
            max_grad_norm=0.5, behave_weight_cap=5.0)
POLICY = PolicySection(kind="mlp", chunk=2, hidden=[8], init_log_std=-0.5, checkpoint="")


def trained(decoupled: bool, stale: bool, prox_logp: str = "recompute", calls: list | None = None) -> torch.Tensor:
    torch.manual_seed(0)
    model = make_policy(POLICY, ObsLayout.vector(4), 1)
    seg = segment([0] * 16)
    obs = torch.as_tensor(seg.obs)
    actions = torch.randn(16, 2, 1)
    with torch.no_grad():
        logp = model.evaluate(obs, actions, torch.zeros(16, 0))[0].numpy()
    if stale:
        logp = logp - 0.3  # the behaviour policy was another one
    seg = TrajectorySegment(**{**seg.__dict__, "actions": actions.numpy(), "logprobs": logp.astype(np.float32),
                               "end": "terminated"})
    ppo = PPO(model, SimpleNamespace(**ALGO, decoupled=decoupled, prox_logp=prox_logp), lr=1e-2, seed=0)
    if calls is not None:  # count the decisions every forward pass evaluates
        net = ppo.net
        ppo.net = lambda method, obs, *rest: calls.append(len(obs)) or net(method, obs, *rest)
    # the behaviour versions are 0; the policy being updated is version 1 when the data is stale
    stats = ppo.update(build_batch([seg], model, 0.9, 0.9), version=1 if stale else 0)
    return torch.cat([p.detach().flatten() for p in model.parameters()]), stats


def test_decoupled_loss_is_plain_ppo_on_policy_and_reweights_stale_data():
    a, stats_a = trained(decoupled=True, stale=False)
    b, _ = trained(decoupled=False, stale=False)
    torch.testing.assert_close(a, b)  # pi_prox == pi_behave: weight 1, same update
    assert stats_a["behave_weight_mean"] == pytest.approx(1.0)
    c, stats_c = trained(decoupled=True, stale=True)
    d, _ = trained(decoupled=False, stale=True)
    assert stats_c["behave_weight_mean"] == pytest.approx(np.exp(0.3), rel=1e-4)
    assert not torch.allclose(c, d)


def test_interpolated_prox_skips_the_recompute_pass_and_is_plain_ppo_on_policy():
    a, stats_a = trained(decoupled=True, stale=False, prox_logp="interpolate")
    b, _ = trained(decoupled=False, stale=False)
    torch.testing.assert_close(a, b)  # alpha = 0: pi_prox = pi_behave
    assert stats_a["behave_weight_mean"] == pytest.approx(1.0)
    recompute_calls, interpolate_calls = [], []
    c, _ = trained(decoupled=True, stale=True, calls=recompute_calls)
    d, stats_d = trained(decoupled=True, stale=True, prox_logp="interpolate", calls=interpolate_calls)
    # one lag of one version: alpha = 1/2, log pi_prox halfway between behaviour and current; the first step
    # sees log pi_theta - log pi_behave = 0.3, so its weight is exp(0.15), and the weights move from there
    assert 1.0 < stats_d["behave_weight_mean"] < np.exp(0.3)
    assert not torch.allclose(c, d)
    steps = ALGO["epochs"] * ALGO["minibatches"]
    assert recompute_calls[0] == 16 and len(recompute_calls) == steps + 1  # the pass over the whole batch
    assert len(interpolate_calls) == steps and sum(interpolate_calls) == ALGO["epochs"] * 16  # ... skipped


def test_the_rollout_length_is_shared_by_the_live_sim_hosts():
    s = resolve(config.from_dict({"train": {"batch_size": 64}}), cores=[0, 1])  # 8 envs: 8 decisions each
    assert [s.length(h) for h in (0, 1, 2, 4, 16)] == [8, 8, 4, 2, 1]
    assert s.min_version(8, hosts=1) == 0 and s.min_version(8, hosts=2) == 1  # two hosts: iterations go twice as fast
