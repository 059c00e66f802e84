"""What training checks before it keeps a segment: one segment, or a vectorized group's packed segments.

A segment's own consistency (fields T long, finite values, counts in range) was checked as it was decoded
(``TrajectorySegment.check``, ``SegmentBatch.check``). What only training can judge is here: a reward no sim sends
(each env step's reward is clipped at ``env.max_abs_reward``, so a decision of k steps carries at most k times it,
an episode of n steps returns at most n times it) and a decision acted by a version this learner never published.
The episodes of the segments taken are followed, and their returns computed, by ``ebrl.algos.returns``.

The rule is written twice, for speed, and a test holds the two to the same verdicts
(``tests/test_bad_numbers.py``): :func:`judge` for one segment in a few scalar operations, :func:`judge_packed`
for the thousands of segments of a packed batch in a few array operations (on one segment the array version
costs more than the scalar one; on a packed batch, far less per segment).
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np

from ebrl.envs.guard import decision_bound
from ebrl.messages import SegmentBatch, TrajectorySegment

TAKEN, REWARD_BOUND, FUTURE_VERSION = 0, 1, 2
REFUSALS = {REWARD_BOUND: "train/reward_bound_dropped", FUTURE_VERSION: "train/future_version_dropped"}
SLACK = 1 + 1e-6  # float32 sums of clipped rewards may round a little above the bound


@dataclass
class Verdict:
    """Each segment and its verdict (:data:`TAKEN`, :data:`REWARD_BOUND`, :data:`FUTURE_VERSION`)."""

    segments: list[TrajectorySegment]
    codes: list[int]


def judge(seg: TrajectorySegment, max_abs_reward: float, version: int) -> Verdict:
    """One segment: over the bound if a decision's reward or an episode's return is above what a sim clipping at
    ``max_abs_reward`` sends; from the future if a decision was acted by a version above ``version``."""
    code = TAKEN
    if (np.abs(seg.rewards.astype(np.float64)) > decision_bound(max_abs_reward, seg.steps)).any() or any(
            abs(ret) > max_abs_reward * max(length, 1) * SLACK
            for ret, length in zip(seg.episode_returns, seg.episode_lengths)):
        code = REWARD_BOUND
    elif int(seg.versions.max()) > version:
        code = FUTURE_VERSION
    return Verdict([seg], [code])


def judge_packed(batch: SegmentBatch, max_abs_reward: float, version: int) -> Verdict:
    """:func:`judge` of every segment of ``batch`` at once."""
    starts = np.cumsum(batch.lengths) - batch.lengths
    over = np.abs(batch.rewards.astype(np.float64)) > decision_bound(max_abs_reward, batch.steps)
    ended = batch.episode_lengths >= 0
    bound = np.logical_or.reduceat(over, starts) | (ended & (
        np.abs(batch.episode_returns.astype(np.float64)) > max_abs_reward * np.maximum(batch.episode_lengths, 1) * SLACK))
    future = np.maximum.reduceat(batch.versions, starts) > version
    codes = np.where(bound, REWARD_BOUND, np.where(future, FUTURE_VERSION, TAKEN))
    return Verdict(batch.segments(), codes.tolist())
