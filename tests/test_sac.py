"""SAC's pieces: the squashed actor within the action bounds, the replay buffer, and the update's rules (targets by
tau, the temperature toward the target entropy, a non-finite step skipped, learning a one-step task)."""

from __future__ import annotations

import math

import numpy as np
import pytest
import torch

from ebrl.algos.replay import (FIELDS, ReplayBatch, ReplayBuffer, ReplayStore, ReplayTooLarge, transition_bytes,
                               transitions)
from ebrl.algos.sac import SAC, SACSettings
from ebrl.config import PolicySection
from ebrl.envs.obs import ObsField, ObsLayout
from ebrl.messages import ReplayRequest, TrajectorySegment
from ebrl.policies import make_policy
from ebrl.policies.squashed import ChunkSquashedMLP

LAYOUT = ObsLayout((ObsField("state", "vector", (3,)),))
LOW, HIGH = np.array([-2.0, 0.0]), np.array([2.0, 1.0])


def actor(chunk: int = 2, seed: int = 0) -> ChunkSquashedMLP:
    torch.manual_seed(seed)
    return ChunkSquashedMLP(LAYOUT, 2, chunk, [32, 32], LOW, HIGH)


def segment(t: int, end: str = "cut", start: float = 0.0, chunk: int = 2) -> TrajectorySegment:
    """``t`` decisions whose observations count up from ``start`` (so each transition's next is recognisable)."""
    obs = (start + np.arange(t, dtype=np.float32))[:, None].repeat(3, 1)
    return TrajectorySegment(
        group=0, env_id=0, episode=0, obs=obs, actions=np.full((t, chunk, 2), 0.5, np.float32),
        latents=np.zeros((t, 0), np.float32), logprobs=np.zeros(t, np.float32), values=np.zeros(t, np.float32),
        rewards=np.arange(t, dtype=np.float32), steps=np.full(t, chunk, np.int32),
        versions=np.arange(t, dtype=np.int64),
        end=end, last_obs=np.full(3, start + t, np.float32), episode_returns=[], episode_lengths=[])


# --- the squashed actor

def test_the_squashed_actor_acts_within_the_bounds_and_its_log_prob_is_the_squashed_densitys():
    policy = actor()
    obs = torch.randn(64, 3) * 5
    actions, logp, values, latents = policy.sample(obs)
    assert actions.shape == (64, 2, 2) and latents.shape == (64, 0) and torch.all(values == 0)
    flat = actions.reshape(64, 2, 2)
    assert torch.all(flat >= torch.as_tensor(LOW, dtype=torch.float32)) and \
        torch.all(flat <= torch.as_tensor(HIGH, dtype=torch.float32))
    again, _, _ = policy.evaluate(obs, actions, latents)  # inverting the squash gives the sampled density back
    torch.testing.assert_close(again, logp, atol=2e-3, rtol=1e-3)
    det = policy.predict_chunk(obs.numpy())
    np.testing.assert_allclose(det, policy.predict_chunk(obs.numpy()))  # the mean: the same each time
    assert det.shape == (64, 2, 2)


def test_the_squashed_kind_needs_bounds_and_refuses_infinite_ones():
    cfg = PolicySection(kind="squashed", chunk=1, hidden=[8], normalize_obs=False)
    with pytest.raises(ValueError, match="action bounds"):
        make_policy(cfg, LAYOUT, 2)
    with pytest.raises(ValueError, match="finite action bounds"):
        make_policy(cfg, LAYOUT, 2, (np.array([-np.inf, 0.0]), np.array([1.0, 1.0])))
    assert make_policy(cfg, LAYOUT, 2, (LOW, HIGH)).kind == "squashed"


# --- the replay buffer

def test_the_replay_keeps_transitions_with_their_next_observation_and_overwrites_the_oldest():
    replay = ReplayBuffer(3, 4, capacity=10)
    assert replay.add(segment(6, end="terminated")) == 6
    batch = replay.sample(200, np.random.default_rng(0))
    np.testing.assert_array_equal(batch.next_obs[:, 0], batch.obs[:, 0] + 1)  # the next decision's, last_obs last
    np.testing.assert_array_equal(batch.terminal, batch.obs[:, 0] == 5)  # only the terminated segment's last
    replay.add(segment(7, start=100.0))
    assert (replay.size, replay.inserted) == (10, 13)
    held = set(replay.obs[:, 0].tolist())
    assert held == {3.0, 4.0, 5.0} | {100.0 + i for i in range(7)}  # the three oldest went
    assert replay.nbytes == 10 * transition_bytes(3, 4)


def test_a_replay_that_would_not_fit_its_bound_is_refused_with_the_numbers():
    with pytest.raises(ReplayTooLarge, match=r"1,000,000 transitions.*MiB.*replay.capacity"):
        ReplayBuffer(100, 4, capacity=1_000_000, max_bytes=64 * 2**20)


def test_a_segment_of_other_sizes_is_refused_and_adds_nothing():
    replay = ReplayBuffer(5, 4, capacity=10)
    with pytest.raises(ValueError, match="this replay holds 5 and 4"):
        replay.add(segment(3))
    assert replay.size == 0


def test_the_replay_saved_is_restored_and_a_bad_file_leaves_it_as_it_was(tmp_path):
    replay = ReplayBuffer(3, 4, capacity=8)
    replay.add(segment(5))
    replay.add(segment(5, start=50.0))
    replay.save(tmp_path / "replay.npz")
    again = ReplayBuffer(3, 4, capacity=8)
    assert again.restore(tmp_path / "replay.npz") == (8, {})
    for name in ("obs", "next_obs", "actions", "rewards", "steps", "terminal", "versions"):
        np.testing.assert_array_equal(getattr(again, name), getattr(replay, name))
    assert (again.cursor, again.inserted) == (replay.cursor, replay.inserted)
    other = ReplayBuffer(3, 2, capacity=8)
    with pytest.raises(ValueError, match="for a replay of"):
        other.restore(tmp_path / "replay.npz")
    assert other.size == 0


# --- the replay service's store

def request(seg: TrajectorySegment | None, seq: int, session: int = 7, acked: int = 0, batches: int = 2,
            batch_size: int = 4) -> ReplayRequest:
    rows = transitions(seg if seg is not None else segment(1))
    rows = {name: value[:0] if seg is None else value for name, value in rows.items()}
    return ReplayRequest(session=session, seq=seq, acked=acked, batches=batches, batch_size=batch_size,
                         **{**rows, "terminal": rows["terminal"].view(np.uint8)})


def test_the_store_adds_a_request_once_though_it_comes_again_and_draws_what_it_holds():
    store = ReplayStore(3, 4, capacity=100)
    empty = store.exchange(request(None, 1))
    assert len(empty.rewards) == 0 and empty.size == 0  # nothing to draw from: no rows, owed on
    first = store.exchange(request(segment(6, end="terminated"), 2))
    assert (first.size, first.inserted, len(first.rewards)) == (6, 6, 8) and first.seq == 2
    assert set(first.obs[:, 0].tolist()) <= set(range(6))
    assert np.all(first.next_obs[:, 0] == first.obs[:, 0] + 1)  # each transition's next observation
    assert np.all(first.terminal == (first.obs[:, 0] == 5))  # only after the episode's last decision
    again = store.exchange(request(segment(6, end="terminated"), 2))  # sent again: not added twice
    assert again.inserted == 6 and store.sampled == 16
    store.exchange(request(segment(3, start=10.0), 1, session=8))  # another session (a restarted train): new
    assert store.buffer.inserted == 9
    with pytest.raises(ValueError, match="this replay holds 3 and 4"):
        store.exchange(request(segment(2, chunk=3), 2, session=8))
    with pytest.raises(ValueError, match="more than the 64 transitions an answer carries"):
        ReplayStore(3, 4, capacity=100, max_rows=64).exchange(request(None, 1, batches=65, batch_size=1))
    assert store.buffer.inserted == 9


def test_a_restarted_store_gets_its_contents_back_and_counts_what_training_saw_it_lose(tmp_path):
    store = ReplayStore(3, 4, capacity=100, seed=1)
    store.exchange(request(segment(10), 1))
    store.save(tmp_path / "replay.npz")
    store.exchange(request(segment(5, start=20.0), 2))  # after the save: lost with the process
    again = ReplayStore(3, 4, capacity=100)
    assert again.restore(tmp_path / "replay.npz") == 10 and again.newest == (7, 1) and again.sampled == 8
    answer = again.exchange(request(segment(5, start=20.0), 2, acked=15))  # sent again to the new process
    assert again.lost == 5 and answer.inserted == 15  # what training saw it hold beyond the file, counted
    np.testing.assert_array_equal(again.buffer.obs[10:15, 0], np.arange(20, 25))
    again.exchange(request(None, 3, acked=15))
    assert again.lost == 5  # counted once
    fresh = ReplayStore(3, 4, capacity=100)  # no file at all: everything training saw is lost
    fresh.exchange(request(None, 4, acked=15))
    assert fresh.lost == 15


# --- the update

def batch(n: int = 64, reward: float = 1.0, seed: int = 0) -> ReplayBatch:
    rng = np.random.default_rng(seed)
    return ReplayBatch(obs=rng.normal(size=(n, 3)).astype(np.float32),
                       actions=rng.uniform(-2, 2, (n, 4)).astype(np.float32) * np.tile([1, 0.25], 2),
                       rewards=np.full(n, reward, np.float32), steps=np.full(n, 2, np.int32),
                       terminal=rng.random(n) < 0.1, next_obs=rng.normal(size=(n, 3)).astype(np.float32),
                       versions=np.zeros(n, np.int64))


def test_a_step_moves_the_targets_by_tau_toward_the_critics():
    sac = SAC(actor(), SACSettings(tau=0.1))
    before = [p.detach().clone() for p in sac.targets.parameters()]
    out = sac.step(batch())
    assert out["steps_skipped"] == 0.0 and math.isfinite(out["critic_loss"]) and "actor_loss" in out
    for old, target, critic in zip(before, sac.targets.parameters(), sac.critics.parameters()):
        torch.testing.assert_close(target, 0.9 * old + 0.1 * critic.detach())
        assert not torch.equal(target, old)


@pytest.mark.parametrize("target_entropy, direction", [(-100.0, -1), (100.0, 1)])
def test_the_temperature_moves_toward_the_target_entropy(target_entropy, direction):
    """Entropy above the target (a very low target): alpha falls; below it: alpha rises."""
    sac = SAC(actor(), SACSettings(target_entropy=target_entropy, lr=1e-2))
    alpha = sac.alpha
    for seed in range(5):
        sac.step(batch(seed=seed))
    assert (sac.alpha - alpha) * direction > 0


def test_a_step_that_is_not_finite_is_skipped_and_moves_nothing():
    sac = SAC(actor(), SACSettings())
    state = {k: v.detach().clone() for k, v in [*sac.critics.state_dict().items(),
                                                 *(("t." + k, v) for k, v in sac.targets.state_dict().items()),
                                                 *(("a." + k, v) for k, v in sac.actor.state_dict().items())]}
    alpha = sac.alpha
    out = sac.step(batch(reward=float("nan")))
    assert out["steps_skipped"] == 1.0 and sac.skipped == 1 and sac.alpha == alpha
    after = {k: v for k, v in [*sac.critics.state_dict().items(),
                               *(("t." + k, v) for k, v in sac.targets.state_dict().items()),
                               *(("a." + k, v) for k, v in sac.actor.state_dict().items())]}
    for name, value in state.items():
        assert torch.equal(after[name], value), name
    assert sac.step(batch())["steps_skipped"] == 0.0  # and the next good step goes ahead


def test_sac_learns_a_one_step_task_and_its_state_restores():
    """Reward -(a - target)^2 on one-step episodes: the deterministic action goes to the target, which sits
    inside the bounds (0.5 of [-2, 2] and 0.7 of [0, 1]). The entropy bonus pulls a bounded action toward the
    middle while alpha is large: the low target entropy and learning rate let alpha fall (to ~0.03) within the test."""
    torch.manual_seed(0)
    policy = ChunkSquashedMLP(LAYOUT, 2, 1, [32, 32], LOW, HIGH)
    sac = SAC(policy, SACSettings(lr=1e-2, critic_hidden=(64, 64), target_entropy=-6.0))
    replay = ReplayBuffer(3, 2, capacity=5000)
    rng, goal = np.random.default_rng(0), np.array([0.5, 0.7], np.float32)
    for _ in range(400):
        obs = rng.normal(size=(16, 3)).astype(np.float32)
        acts = policy.sample(torch.as_tensor(obs))[0].detach().numpy()
        rewards = -((acts[:, 0] - goal) ** 2).sum(-1)
        for o, a, r in zip(obs, acts, rewards):
            replay.add(TrajectorySegment(group=0, env_id=0, episode=0, obs=o[None], actions=a[None],
                                         latents=np.zeros((1, 0), np.float32), logprobs=np.zeros(1, np.float32),
                                         values=np.zeros(1, np.float32), rewards=np.array([r], np.float32),
                                         steps=np.ones(1, np.int32), versions=np.zeros(1, np.int64),
                                         end="terminated", last_obs=o, episode_returns=[], episode_lengths=[]))
        sac.step(replay.sample(128, rng))
    learned = policy.predict_chunk(rng.normal(size=(32, 3)).astype(np.float32))[:, 0]
    np.testing.assert_allclose(learned.mean(0), goal, atol=0.08)  # 3 seeds: within 0.03
    again = SAC(ChunkSquashedMLP(LAYOUT, 2, 1, [32, 32], LOW, HIGH), SACSettings(critic_hidden=(64, 64)))
    again.load_state(sac.state())
    assert again.alpha == pytest.approx(sac.alpha)
    for a, b in zip(again.targets.parameters(), sac.targets.parameters()):
        assert torch.equal(a, b)


def test_in_the_warm_up_the_actor_samples_uniformly_within_the_bounds_and_predicts_as_ever():
    model = actor(chunk=1)
    obs = np.zeros((4000, 3), np.float32)
    with torch.no_grad():  # as generation acts
        acting = model.sample(obs)[0].numpy().reshape(-1, 2)
        model.warmup.fill_(1.0)
        warm = model.sample(obs)[0].numpy().reshape(-1, 2)
    low, high = LOW, HIGH
    assert np.all((warm >= low) & (warm <= high))
    assert np.allclose(warm.mean(0), (low + high) / 2, atol=0.06) and np.allclose(warm.std(0), (high - low) / 12 ** 0.5,
                                                                                 atol=0.05)
    assert not np.allclose(acting.std(0), warm.std(0), atol=0.05)  # the actor's own samples are not uniform
    assert np.array_equal(model.predict_chunk(obs[:3]), actor(chunk=1).predict_chunk(obs[:3]))


def test_under_bfloat16_autocast_a_saturated_actor_keeps_finite_log_probs_and_steps():
    model = actor()
    with torch.no_grad():
        model.mean.bias.fill_(20.0)  # tanh(u) rounds to exactly 1 in bfloat16
    sac = SAC(model, SACSettings())
    with torch.autocast("cpu", dtype=torch.bfloat16):
        _, logp = model.rsample(torch.zeros(64, 3))
        out = sac.step(batch())
    assert torch.isfinite(logp).all()
    assert out["steps_skipped"] == 0.0
