"""Training computes the returns it decides on (``ebrl/algos/returns.py``): an episode's return is the sum of the
rewards training received, followed segment by segment; a forged return, a replay or a cut segment that claims an
episode is refused; a gap leaves the episode uncounted; a reward past the bound keeps its episode out of the
statistics a run ends on. Real segments, built as a simulator builds them, go through the real learner."""

from __future__ import annotations


import numpy as np
import pytest

from ebrl.algos.learner import Learner
from ebrl.algos.returns import LEARN_AFTER, EpisodeLedger, Pieces, RewardBound
from ebrl.config import Config
from ebrl.envs import EnvSpec, describe
from ebrl.envs.worker import ChunkResult
from ebrl.messages import TrajectorySegment
from ebrl.sched.rollout import SegmentBuilder
from helpers import Counts
from test_bad_numbers import pack  # a vectorized group's packed message of these segments

CFG = Config()  # InvertedPendulum-v5: 1 per step, no declared range
INFO = describe(EnvSpec.from_config(CFG.env))
K = CFG.policy.chunk


def episode(env: int, index: int, rewards: list[float], length: int = 4, end: str = "terminated"
            ) -> list[TrajectorySegment]:
    """One env's episode of ``len(rewards)`` decisions of K steps as a simulator's builder cuts it (segments of
    ``length`` decisions), each step's reward its decision's over K; ``end``: how it ends ("cut": not yet)."""
    builder, out = SegmentBuilder(0, env, length), []
    obs = np.zeros(INFO.obs_shape, np.float32)
    total = 0.0
    for t, r in enumerate(rewards):
        last = t == len(rewards) - 1 and end != "cut"
        total += r
        result = ChunkResult(r, K, last and end == "terminated", last and end == "truncated", obs, obs,
                             total if last else None, (t + 1) * K if last else None, episode=index,
                             episode_success=(r > 0) if last else None)
        seg = builder.add(obs, np.zeros((K, INFO.action_dim), np.float32), np.zeros(0, np.float32), 0.0, 0.0, 0,
                          result)
        if seg is not None:
            out.append(seg)
    return out


def learner(tmp_path, **env) -> tuple[Learner, Counts]:
    cfg = Config()
    for name, value in env.items():
        setattr(cfg.env, name, value)
    telemetry = Counts()
    return Learner(cfg, INFO, 4, telemetry, str(tmp_path)), telemetry


def test_a_return_is_the_sum_of_the_rewards_training_received_over_the_episodes_segments(tmp_path):
    learn, counts = learner(tmp_path, reward_bound=10.0)
    segments = episode(0, 0, [1.0] * 10) + episode(1, 0, [2.0, 0.5, 0.25])  # 3 segments, then 1
    assert [s.episode_offset for s in segments] == [0, 4 * K, 8 * K, 0]
    assert sum(learn.accept(s, pytest.fail) for s in segments) == 4
    m = learn.metrics()
    assert (m["train/episode_return_mean"], m["train/episodes"], m["train/episode_length_max"]) == (
        pytest.approx((10.0 + 2.75) / 2), 2, 10 * K)
    assert m["train/env_steps"] == 13 * K and m["train/segments_g0"] == 4
    assert m["train/episode_values_refused"] == m["train/segments_replayed"] == m["train/episodes_incomplete"] == 0


def test_forged_episode_values_in_real_segments_are_refused_and_never_counted(tmp_path):
    """The issue's case: copies of one real segment (rewards summing to a few) each claiming finished episodes of a
    return of 1000, and a cut segment that claims one: refused, counted, the mean return untouched."""
    learn, counts = learner(tmp_path, reward_bound=10.0)
    real = episode(0, 0, [1.0] * 3)[0]
    assert learn.accept(real, pytest.fail)
    forged = []
    for env in range(1, 6):
        seg = episode(env, 0, [1.0] * 3)[0]
        seg.episode_returns = [1000.0]  # its rewards sum to 3
        forged.append(seg)
    many = episode(6, 0, [1.0] * 3)[0]
    many.episode_returns, many.episode_lengths = [1000.0] * 20, [3 * K] * 20  # 20 episodes in one segment
    many.episode_successes = [True] * 20
    forged.append(many)
    cut = episode(7, 0, [1.0] * 4, end="cut")[0]
    cut.episode_returns, cut.episode_lengths = [4.0], [4 * K]  # a segment that did not end an episode claims one
    long = episode(8, 0, [1.0] * 3)[0]
    long.episode_lengths = [400]  # the right return, a length its steps do not make
    assert not any(learn.accept(s, pytest.fail) for s in [*forged, cut, long])
    m = learn.metrics()
    assert m["train/episode_values_refused"] == 8 and m["train/episodes"] == 1
    assert m["train/episode_return_mean"] == 3.0
    assert counts.counts["train/segments_received"] == 1  # none of them trained on


def test_a_replayed_segment_is_refused_and_a_gap_leaves_its_episode_uncounted(tmp_path):
    learn, counts = learner(tmp_path, reward_bound=10.0)
    a, b, c = episode(0, 3, [1.0] * 10)
    assert learn.accept(a, pytest.fail) and learn.accept(b, pytest.fail)
    assert not learn.accept(b, pytest.fail) and not learn.accept(a, pytest.fail)  # steps already received
    assert learn.accept(c, pytest.fail)
    assert not learn.accept(c, pytest.fail)  # after its episode's end
    x, _, z = episode(1, 0, [1.0] * 10)  # the middle segment never arrives (a simulator died, say)
    assert learn.accept(x, pytest.fail) and learn.accept(z, pytest.fail)  # trained on ...
    late = episode(2, 5, [1.0] * 10)[1:]  # a training that started in the middle of env 2's episode
    assert all(learn.accept(s, pytest.fail) for s in late)
    m = learn.metrics()
    assert m["train/segments_replayed"] == 3 and m["train/episodes"] == 1  # ... not counted
    assert m["train/episodes_incomplete"] == 2 and m["train/episode_return_mean"] == 10.0
    # a simulator that started again numbers episodes from 0 again: a new episode, counted
    assert all(learn.accept(s, pytest.fail) for s in episode(0, 0, [2.0] * 5))
    assert learn.metrics()["train/episodes"] == 2


def test_a_reward_past_the_bound_keeps_its_episode_out_of_the_statistics_but_in_training(tmp_path):
    """The bad-numbers case: a buggy env's 1e38 reward clipped by the simulator to env.max_abs_reward (1e6) in one
    episode. With a learned bound (InvertedPendulum declares no range), its episode is trained on and not counted;
    episodes that end before the bound is known wait for it."""
    learn, counts = learner(tmp_path)
    early = episode(0, 0, [K * 1.0] * 3)  # reward 1 per step
    absurd = episode(1, 0, [K * 1.0, 1e6, K * 1.0])
    for seg in early + absurd:
        assert learn.accept(seg, pytest.fail)
    assert "train/episode_return_mean" not in learn.metrics()  # no bound yet: nothing counts
    env = 2
    while "train/reward_bound" not in learn.metrics():  # LEARN_AFTER nonzero decision rewards
        for seg in episode(env, 0, [K * 1.0] * 8):
            learn.accept(seg, pytest.fail)
        env += 1
    assert (env - 2) * 8 + 6 >= LEARN_AFTER
    m = learn.metrics()
    assert m["train/reward_bound"] == pytest.approx(1000.0)  # 1000 x the 90th percentile of 1 per step
    assert m["train/episodes_past_bound"] == 1 and m["train/episode_return_mean"] == 8.0 * K
    assert max(learn.intake.ledger.returns) < 1e6
    assert counts.counts["train/segments_received"] == 2 + 2 * (env - 2)  # every segment, the absurd one too
    counts_before = learn.metrics()["train/episodes_past_bound"]
    for seg in episode(env, 0, [K * 1.0, 1e6]):
        learn.accept(seg, pytest.fail)
    assert learn.metrics()["train/episodes_past_bound"] == counts_before + 1  # judged at once from now on


def test_the_bound_comes_from_the_env_s_declared_range_or_the_config_or_is_learned_robustly():
    assert RewardBound("auto", (0.0, 1.0)).value == pytest.approx(1.0)
    assert RewardBound("auto", (-16.3, 0.0)).value == pytest.approx(16.3)
    assert RewardBound(50.0, (0.0, 1.0)).value == 50.0 and not RewardBound(50.0).learns
    assert RewardBound(float("inf")).value == float("inf") and not RewardBound(float("inf")).learns
    learned = RewardBound("auto")
    rng = np.random.default_rng(0)
    magnitudes = rng.uniform(0.0, 2.0, LEARN_AFTER)
    magnitudes[::20] = 2.5e5  # a buggy env's absurd rewards in 5 % of the decisions
    assert learned.value is None and learned.observe(magnitudes)
    assert 1000.0 < learned.value < 3000.0  # 1000 x the 90th percentile, not the outliers'
    assert not learned.observe(np.full(LEARN_AFTER, 2.5e5))  # past the bound: not learned from
    assert learned.observe(np.full(LEARN_AFTER, 10.0)) and learned.value == pytest.approx(10_000.0)  # it grows ...
    assert not learned.observe(np.full(LEARN_AFTER, 0.001))  # ... never shrinks
    sparse = RewardBound("auto")
    assert not sparse.observe(np.zeros(10 * LEARN_AFTER))  # zero rewards teach nothing


def test_packed_segments_are_followed_as_the_same_segments_one_at_a_time():
    rng = np.random.default_rng(3)
    envs = {env: [s for i in range(4) for s in episode(env, i, list(rng.uniform(0, 2, rng.integers(1, 12))))]
            for env in range(6)}
    envs[2][1].episode_returns = [99.0] if envs[2][1].episode_returns else []
    envs[3].insert(2, envs[3][1])  # a replay
    del envs[4][1]  # a gap
    one, packed = EpisodeLedger(RewardBound(10.0)), EpisodeLedger(RewardBound(10.0))
    single = []
    rounds = max(len(s) for s in envs.values())
    for r in range(rounds):  # one packed batch per round: each env's r-th segment
        batch = [s[r] for s in envs.values() if r < len(s)]
        for seg in batch:
            single.append(int(one.follow(Pieces.of_segment(seg), np.ones(1, bool))[0]))
        packed.follow(Pieces.of_batch(pack(batch)), np.ones(len(batch), bool))
    assert one.metrics() == packed.metrics()
    assert list(one.returns) == list(packed.returns) and one.counts["train/segments_replayed"] == 1
    assert one.counts["train/episodes_incomplete"] >= 1
