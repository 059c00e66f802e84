"""Episode returns as training computes them: from the rewards and env steps of the segments it received, never
from what a segment says.

The simulator runs the user's env code, the least trusted code of a run, and a run ends on training's mean
return (``run.target_return``). So training follows each env's episode itself, segment by segment, by the
segment's ``episode_offset`` (env steps of its episode before it):

* a segment with offset 0 opens its episode; one whose offset is where the env's last segment of the same
  episode ended continues it; the episode's return is training's own float64 sum of their rewards;
* a segment that repeats an episode's steps already received, or comes after its end, is a replay: refused
  (``train/segments_replayed``) -- except the first segment of an env's episode 0, which opens it anew: a
  simulator that started again numbers its episodes from 0;
* a segment after a gap (one refused, one lost with a simulator that died, a training that started in the middle
  of an episode, an offset not reported) leaves its episode incomplete: trained on, but the episode does not
  count (``train/episodes_incomplete``);
* where a segment ends its episode, the return and length it reports must be training's own (the return to float
  rounding, the length exactly), and only a terminated or truncated segment may report one: else the segment is
  refused (``train/episode_values_refused``) -- a forged return is never believed, the real one never replaced;
* an episode with a reward past the bound (:class:`RewardBound`) is trained on but does not count toward the
  return statistics and targets (``train/episodes_past_bound``): a buggy env's one absurd reward, clipped to
  ``env.max_abs_reward`` by the simulator, cannot end a run as if it had reached its target.

A segment is described by the same arrays whether it came alone or packed (:class:`Pieces`), and followed with
array operations: the thousands of segments of a GPU batch cost a few array passes, one segment a few more
microseconds than before.
"""

from __future__ import annotations

import collections
import math
from dataclasses import dataclass

import numpy as np

from ebrl.messages import RETURN_WINDOW, SEGMENT_ENDS, SegmentBatch, TrajectorySegment

CUT = SEGMENT_ENDS.index("cut")
RETURN_RTOL, RETURN_ATOL = 1e-4, 1e-4  # float32 rewards summed by sim and by train: rounding, not forgery
LEARN_AFTER = 1000  # nonzero decision rewards before an "auto" bound is learned
LEARN_FACTOR = 1000.0  # the learned bound: this x the 90th percentile of their per-step magnitude
LEARN_QUANTILE = 0.9  # robust to a buggy env's absurd rewards in up to a tenth of the decisions
RING = 4096  # the latest nonzero per-step magnitudes the learned bound is re-derived from
# episodes that ended before an "auto" bound was known, judged once it is: each of them brought at least one nonzero
# reward to learn it from, so fewer than LEARN_AFTER wait (and a batch's own; the bound is learned before they join)
PENDING_MAX = 4 * LEARN_AFTER


@dataclass
class Pieces:
    """What training needs of ``S`` segments to follow their episodes, one row each (from a packed batch, or a
    single segment as one row)."""

    env_ids: np.ndarray  # int64 [S]
    episodes: np.ndarray  # int64 [S]
    offsets: np.ndarray  # int64 [S]; -1 not reported
    rewards: np.ndarray  # float64 [S]: the segment's sum of decision rewards
    steps: np.ndarray  # int64 [S]: its env steps
    peaks: np.ndarray  # float64 [S]: its largest decision reward per env step, in magnitude
    ends: np.ndarray  # int8 [S]: SEGMENT_ENDS codes
    reported: np.ndarray  # bool [S]: it reports an episode's end
    returns: np.ndarray  # float64 [S]: the reported return (where reported)
    lengths: np.ndarray  # int64 [S]: the reported length (where reported)
    successes: np.ndarray  # int8 [S]: 1, 0, -1 (none)
    malformed: np.ndarray  # bool [S]: reports more than the one episode a segment can end

    @classmethod
    def of_batch(cls, batch: SegmentBatch) -> "Pieces":
        starts = np.cumsum(batch.lengths, dtype=np.int64) - batch.lengths
        rewards = batch.rewards.astype(np.float64)
        steps = batch.steps.astype(np.int64)
        reported = batch.episode_lengths >= 0
        return cls(batch.env_ids.astype(np.int64), batch.episodes.astype(np.int64),
                   batch.episode_offsets.astype(np.int64), np.add.reduceat(rewards, starts),
                   np.add.reduceat(steps, starts), np.maximum.reduceat(np.abs(rewards) / np.maximum(steps, 1), starts),
                   batch.ends.astype(np.int8), reported, batch.episode_returns.astype(np.float64),
                   batch.episode_lengths.astype(np.int64), batch.episode_successes.astype(np.int8),
                   np.zeros(len(batch.env_ids), bool))

    @classmethod
    def of_segment(cls, seg: TrajectorySegment) -> "Pieces":
        rewards, steps = seg.rewards.astype(np.float64), seg.steps.astype(np.int64)
        n = len(seg.episode_returns)
        success = seg.episode_successes[0] if n == 1 and seg.episode_successes else None
        return cls(np.array([seg.env_id], np.int64), np.array([seg.episode], np.int64),
                   np.array([seg.episode_offset], np.int64), np.array([rewards.sum()]), np.array([steps.sum()]),
                   np.array([(np.abs(rewards) / np.maximum(steps, 1)).max()]),
                   np.array([SEGMENT_ENDS.index(seg.end)], np.int8), np.array([n >= 1]),
                   np.array([seg.episode_returns[0] if n else 0.0], np.float64),
                   np.array([seg.episode_lengths[0] if n else -1], np.int64),
                   np.array([-1 if success is None else int(success)], np.int8), np.array([n > 1]))


class RewardBound:
    """The largest reward magnitude of one env step that an episode may carry and still count (``env.reward_bound``):
    a number given; the env's declared range (``declared``); or, for ``"auto"`` without one, learned from the run's
    own rewards -- :data:`LEARN_FACTOR` x the :data:`LEARN_QUANTILE` quantile of the per-step magnitude of the first
    :data:`LEARN_AFTER` nonzero decision rewards, re-derived from the latest :data:`RING` within it as more come,
    never lower. Unknown (None) until then."""

    def __init__(self, setting: float | str, declared: tuple[float, float] | None = None):
        self.learns = setting == "auto" and declared is None
        if setting != "auto":
            self.value: float | None = float(setting)
        elif declared is not None:
            self.value = max(abs(declared[0]), abs(declared[1])) * (1 + 1e-6)
        else:
            self.value = None
        self._ring = np.zeros(RING)
        self._n = 0  # magnitudes seen (the ring holds the latest RING)
        self._since = 0  # since the bound was last derived

    def observe(self, magnitudes: np.ndarray) -> bool:
        """Take decision rewards' per-step magnitudes (of segments taken); True when the bound became known or
        moved. A magnitude past a known bound is not learned from."""
        if not self.learns:
            return False
        m = magnitudes[magnitudes > 0]
        if self.value is not None:
            m = m[m <= self.value]
        if not len(m):
            return False
        m = m[-RING:]
        at = (self._n + np.arange(len(m))) % RING
        self._ring[at] = m
        self._n += len(m)
        self._since += len(m)
        if self._n < LEARN_AFTER or (self.value is not None and self._since < LEARN_AFTER):
            return False
        self._since = 0
        learned = LEARN_FACTOR * float(np.quantile(self._ring[:min(self._n, RING)], LEARN_QUANTILE))
        if self.value is not None and learned <= self.value:
            return False
        self.value = learned
        return True


class EpisodeLedger:
    """Each env's current episode as training received it, and the episodes that count: the latest
    ``RETURN_WINDOW`` counted returns and successes, and the counters of the module's doc."""

    def __init__(self, bound: RewardBound):
        self.bound = bound
        self._row: dict[int, int] = {}  # env id -> row of the arrays below
        self.episode = np.zeros(0, np.int64)  # its current episode
        self.expect = np.zeros(0, np.int64)  # the offset its next segment has (-1: unknown)
        self.total = np.zeros(0, np.float64)  # the episode's return so far
        self.peak = np.zeros(0, np.float64)  # its largest reward per step so far
        self.complete = np.zeros(0, bool)  # every segment of the episode so far received and taken
        self.closed = np.zeros(0, bool)  # the episode ended
        self.returns: collections.deque[float] = collections.deque(maxlen=RETURN_WINDOW)
        self.successes: collections.deque[bool] = collections.deque(maxlen=RETURN_WINDOW)
        self.pending: collections.deque[tuple[float, float, int, int]] = collections.deque(maxlen=PENDING_MAX)
        self.counted = 0  # episodes counted
        self.longest = 0  # env steps of the longest episode counted
        self.counts = {"train/segments_replayed": 0, "train/episode_values_refused": 0,
                       "train/episodes_incomplete": 0, "train/episodes_past_bound": 0}

    def _rows(self, env_ids: np.ndarray) -> np.ndarray:
        rows = np.empty(len(env_ids), np.int64)
        for i, env in enumerate(env_ids.tolist()):
            row = self._row.get(env)
            if row is None:
                row = self._row[env] = len(self._row)
            rows[i] = row
        if len(self._row) > len(self.episode):  # grow, doubling
            n = max(2 * len(self.episode), len(self._row), 64)
            for name, fill in (("episode", -1), ("expect", -1), ("total", 0.0), ("peak", 0.0), ("complete", False),
                               ("closed", False)):
                old = getattr(self, name)
                new = np.full(n, fill, old.dtype)
                new[:len(old)] = old
                setattr(self, name, new)
        return rows

    def follow(self, pieces: Pieces, taken: np.ndarray, rewards_per_step: np.ndarray | None = None) -> np.ndarray:
        """Follow segments whose env ids are distinct (a packed batch's; a single segment's) through their
        episodes. ``taken``: the segments training's other checks took (a refused one breaks its episode).
        ``rewards_per_step``: the taken decisions' per-step reward magnitudes, for a learned bound. Returns the
        verdict of this module per segment: 0 followed, 1 a replay, 2 episode values that are not training's
        (both refused)."""
        rows = self._rows(pieces.env_ids)
        expect, closed = self.expect[rows], self.closed[rows]
        offsets, same = pieces.offsets, self.episode[rows] == pieces.episodes
        # steps already received; an episode's first segment again too, except in episode 0, which a simulator
        # that started again numbers from anew
        replay = same & (closed | ((offsets > 0) & (offsets < expect)) | ((offsets == 0) & (pieces.episodes > 0)))
        fresh = (offsets == 0) & ~replay
        goes_on = same & ~closed & (offsets > 0) & (offsets == expect) & ~replay
        total = np.where(goes_on, self.total[rows] + pieces.rewards, pieces.rewards)
        peak = np.where(goes_on, np.maximum(self.peak[rows], pieces.peaks), pieces.peaks)
        complete = np.where(goes_on, self.complete[rows], fresh) & taken
        ends = pieces.ends != CUT
        length = np.where(offsets >= 0, offsets + pieces.steps, -1)
        wrong = pieces.malformed | (pieces.reported & (~ends | ((offsets >= 0) & (pieces.lengths != length)) | (
            complete & (np.abs(pieces.returns - total) > RETURN_RTOL * (np.abs(total) + np.abs(pieces.returns))
                        + RETURN_ATOL))))
        wrong &= ~replay
        verdict = np.where(replay, 1, np.where(wrong, 2, 0))
        keep = ~replay  # a replay leaves the episode as it was
        at = rows[keep]
        self.episode[at] = pieces.episodes[keep]
        self.expect[at] = np.where(ends | wrong, -1, length)[keep]
        self.total[at], self.peak[at] = total[keep], peak[keep]
        self.complete[at] = (complete & ~wrong)[keep]
        self.closed[at] = (ends | wrong)[keep]
        self.counts["train/segments_replayed"] += int(replay.sum())
        self.counts["train/episode_values_refused"] += int(wrong.sum())
        if rewards_per_step is not None and self.bound.observe(rewards_per_step) and self.pending:
            for item in list(self.pending):
                self._judge(*item)
            self.pending.clear()
        done = ends & ~replay & ~wrong
        self.counts["train/episodes_incomplete"] += int((done & ~(complete & pieces.reported)).sum())
        for i in np.flatnonzero(done & complete & pieces.reported).tolist():
            item = (float(total[i]), float(peak[i]), int(length[i]), int(pieces.successes[i]))
            if self.bound.value is None and self.bound.learns and item[1] > 0:  # all-zero rewards: within any
                self.pending.append(item)
            else:
                self._judge(*item)
        return verdict

    def _judge(self, total: float, peak: float, length: int, success: int) -> None:
        """A whole episode, its values training's own: counted, or past the bound."""
        if self.bound.value is not None and peak > self.bound.value:
            self.counts["train/episodes_past_bound"] += 1
            return
        self.returns.append(total)
        if success >= 0:
            self.successes.append(bool(success))
        self.counted += 1
        self.longest = max(self.longest, length)

    def metrics(self) -> dict[str, float]:
        out = {name: float(n) for name, n in self.counts.items()}
        if self.bound.value is not None and math.isfinite(self.bound.value):
            out["train/reward_bound"] = self.bound.value
        if self.returns:
            out["train/episode_return_mean"] = float(np.mean(self.returns))
            out["train/episodes"] = float(self.counted)
            out["train/episode_length_max"] = float(self.longest)
        if self.successes:
            out["train/success_rate"] = float(np.mean(self.successes))
        return out
