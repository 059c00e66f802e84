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

from ebrl.algos.returns import EpisodeLedger, Pieces
from ebrl.envs.guard import decision_bound
from ebrl.meter import Telemetry
from ebrl.messages import SegmentBatch, TrajectorySegment

TAKEN, REWARD_BOUND, FUTURE_VERSION = 0, 1, 2
REFUSALS = {REWARD_BOUND: "train/reward_bound_dropped", FUTURE_VERSION: "train/future_version_dropped"}
SLACK = 1 + 1e-6  # float32 sums of clipped rewards may round a little above the bound
MAX_GROUPS_SHOWN = 256  # groups with their own train/segments_g<group> count (a report's names are bounded)


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


class Intake:
    """What training takes in: each segment judged (:func:`judge`, :func:`judge_packed`) and its episode followed,
    its return computed, by the ``ledger`` (``ebrl.algos.returns``: a replay or a forged return is refused there);
    the env steps of the segments taken (``train/env_steps``) and the segments decoded from each group, taken or
    not (``train/segments_g<group>``: evidence the stall watch judges a simulator on)."""

    def __init__(self, max_abs_reward: float, ledger: EpisodeLedger, telemetry: Telemetry):
        self.max_abs_reward, self.ledger, self.telemetry = max_abs_reward, ledger, telemetry
        self.env_steps = 0
        self.by_group: dict[int, int] = {}

    def take(self, item: TrajectorySegment | SegmentBatch, version: int, handed: bool = False
             ) -> list[TrajectorySegment]:
        """The segments of ``item`` to learn from, the others dropped and counted. ``handed``: handed over by the
        learner before (counted there: not again)."""
        packed = isinstance(item, SegmentBatch)
        verdict = (judge_packed if packed else judge)(item, self.max_abs_reward, version)  # type: ignore[arg-type]
        if not handed and (item.group in self.by_group or len(self.by_group) < MAX_GROUPS_SHOWN):
            self.by_group[item.group] = self.by_group.get(item.group, 0) + len(verdict.segments)
        for code, name in REFUSALS.items():  # rewards no sim sends (env.max_abs_reward clips them), or acted by
            if n := verdict.codes.count(code):  # weights never published
                self.telemetry.count(name, n)
        ok = np.asarray(verdict.codes) == TAKEN
        per_step = np.abs(item.rewards) / np.maximum(item.steps, 1)  # a learned reward bound reads these
        if not ok.all():
            per_step = per_step[np.repeat(ok, item.lengths) if packed else np.zeros(0, np.int64)]
        followed = self.ledger.follow(Pieces.of_batch(item) if packed else Pieces.of_segment(item), ok, per_step)
        good = ok & (followed == 0)
        taken = [seg for seg, keep in zip(verdict.segments, good.tolist()) if keep]
        if taken and not handed:
            self.telemetry.count("train/segments_received", len(taken))
            self.env_steps += int(item.steps[np.repeat(good, item.lengths)].sum() if packed else item.steps.sum())
        return taken

    def metrics(self) -> dict[str, float]:
        return {**self.ledger.metrics(), "train/env_steps": float(self.env_steps),
                **{f"train/segments_g{group}": float(n) for group, n in self.by_group.items()}}
