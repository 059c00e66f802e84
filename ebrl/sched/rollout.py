"""Trajectory assembly: one builder per environment turns chunk results into segments."""

from __future__ import annotations

import asyncio
from dataclasses import dataclass, field

import numpy as np

from ebrl.envs.worker import ChunkResult, VectorChunk
from ebrl.messages import SEGMENT_ENDS, ActionChunk, SegmentBatch, TrajectorySegment


@dataclass
class SegmentBuilder:
    """Collects one environment's chunk decisions; emits a segment at episode end or at ``length``."""

    group: int
    env_id: int
    length: int
    _obs: list[np.ndarray] = field(default_factory=list)
    _actions: list[np.ndarray] = field(default_factory=list)
    _latents: list[np.ndarray] = field(default_factory=list)
    _logprobs: list[float] = field(default_factory=list)
    _values: list[float] = field(default_factory=list)
    _rewards: list[float] = field(default_factory=list)
    _steps: list[int] = field(default_factory=list)
    _versions: list[int] = field(default_factory=list)
    _returns: list[float] = field(default_factory=list)
    _lengths: list[int] = field(default_factory=list)
    _successes: list[bool | None] = field(default_factory=list)
    _episode: int = 0
    _offset: int = 0  # env steps of the episode before the segment being built
    _in_episode: int = 0  # env steps of the episode so far
    _last_episode: int = -1  # the episode of the latest decision

    def __len__(self) -> int:
        return len(self._obs)

    def add(self, obs: np.ndarray, action: np.ndarray, latent: np.ndarray, logprob: float, value: float,
            version: int, result: ChunkResult, boundary: bool = False) -> TrajectorySegment | None:
        """Record one chunk decision and what the environment did; return a finished segment or None.
        ``boundary`` marks the last decision of an iteration: the segment is cut there so that every
        decision of the iteration reaches training."""
        if not self._obs:
            if result.episode != self._last_episode:  # a new episode (or a replaced worker's next one)
                self._in_episode = 0
            self._episode, self._offset = result.episode, self._in_episode
        self._last_episode = result.episode
        self._in_episode += int(result.steps)
        self._obs.append(obs)
        self._actions.append(action)
        self._latents.append(latent)
        self._logprobs.append(logprob)
        self._values.append(value)
        self._rewards.append(result.reward)
        self._steps.append(result.steps)
        self._versions.append(version)
        if result.episode_return is not None:
            self._returns.append(result.episode_return)
            self._lengths.append(int(result.episode_length))
            self._successes.append(result.episode_success)
        if result.terminated:
            return self._emit("terminated", result.final_obs)
        if result.truncated:
            return self._emit("truncated", result.final_obs)
        if len(self._obs) >= self.length or boundary:
            return self._emit("cut", result.next_obs)
        return None

    def _emit(self, end: str, last_obs: np.ndarray) -> TrajectorySegment:
        segment = TrajectorySegment(
            group=self.group,
            env_id=self.env_id,
            episode=self._episode,
            obs=np.stack(self._obs).astype(np.float32),
            actions=np.stack(self._actions).astype(np.float32),
            latents=np.stack(self._latents).astype(np.float32),
            logprobs=np.asarray(self._logprobs, dtype=np.float32),
            values=np.asarray(self._values, dtype=np.float32),
            rewards=np.asarray(self._rewards, dtype=np.float32),
            steps=np.asarray(self._steps, dtype=np.int32),
            versions=np.asarray(self._versions, dtype=np.int64),
            end=end,  # type: ignore[arg-type]
            last_obs=np.asarray(last_obs, dtype=np.float32),
            episode_returns=list(self._returns),
            episode_lengths=list(self._lengths),
            episode_successes=list(self._successes),
            episode_offset=self._offset,
        )
        for buf in (self._obs, self._actions, self._latents, self._logprobs, self._values, self._rewards, self._steps,
                    self._versions, self._returns, self._lengths, self._successes):
            buf.clear()
        return segment


class SegmentBuffers:
    """:class:`SegmentBuilder` for all ``n`` envs of a vectorized group at once, in arrays: each chunk's decisions
    go in with one write per field, and the segments that end at it (the same cuts, each env's own) come out as
    :class:`~ebrl.messages.SegmentBatch` messages of at most about ``PACKED_BYTES`` each. A builder per env costs a
    few microseconds of Python per env and chunk, and a message per segment as much again on both sides of the bus:
    at a GPU batch's thousands of envs that was most of a chunk's time (``benchmarks/vector_transfer.py``)."""

    def __init__(self, group: int, env_ids: np.ndarray, length: int):
        self.group, self.env_ids, self.length = group, np.asarray(env_ids, np.int64), length
        n = len(self.env_ids)
        self.fill = np.zeros(n, np.int64)  # decisions of each env's current segment
        self.episode = np.zeros(n, np.int64)  # the episode each env's current segment belongs to
        self.offset = np.zeros(n, np.int64)  # env steps of that episode before the current segment
        self.in_episode = np.zeros(n, np.int64)  # env steps of each env's episode so far
        self.last_episode = np.full(n, -1, np.int64)  # the episode of each env's latest decision
        self.rows = np.arange(n)
        self.bufs: dict[str, np.ndarray] = {}  # field -> [n, length, ...], made at the first chunk

    def __len__(self) -> int:
        """Decisions in the segments not yet emitted."""
        return int(self.fill.sum())

    def drop(self) -> int:
        """Forget every segment in progress (the group's process was replaced); the decisions dropped."""
        dropped, self.fill[:] = len(self), 0
        return dropped

    def add(self, obs: np.ndarray, chunk: ActionChunk, result: VectorChunk, boundary: bool = False
            ) -> list[SegmentBatch]:
        """Record every env's decision (``obs`` [n, ...] before the chunk, ``chunk`` the actions that answered it,
        ``result`` what the batch did); the segments that end here, packed (none: an empty list). A segment ends as
        a builder's does: at its episode's end, at ``length`` decisions, or at an iteration ``boundary``."""
        n, fill, rows = len(self.env_ids), self.fill, self.rows
        per_decision = {"obs": obs, "actions": chunk.actions, "latents": chunk.latents, "logprobs": chunk.logprobs,
                        "values": chunk.values, "rewards": result.reward, "steps": result.steps,
                        "versions": np.full(n, chunk.policy_version, np.int64)}
        if not self.bufs:  # env-major, [n, length, ...]: a segment's decisions lie together
            self.bufs = {name: np.zeros((n, self.length, *np.shape(value)[1:]), DTYPES[name])
                         for name, value in per_decision.items()}
        starting = fill == 0
        episode = np.asarray(result.episode, np.int64)
        self.in_episode[starting & (episode != self.last_episode)] = 0  # a new episode (or after a replacement)
        self.episode[starting] = episode[starting]
        self.offset[starting] = self.in_episode[starting]
        self.last_episode[:] = episode
        self.in_episode += np.asarray(result.steps, np.int64)
        at = (slice(None), int(fill[0])) if int(fill.min()) == int(fill.max()) else (rows, fill)  # in step: a slice
        for name, value in per_decision.items():
            self.bufs[name][at] = value
        fill += 1
        terminated = np.asarray(result.terminated, bool)
        truncated = np.asarray(result.truncated, bool) & ~terminated
        emit = np.flatnonzero(terminated | truncated | (fill >= self.length) | boundary)
        if not len(emit):
            return []
        code = SEGMENT_ENDS.index
        ends = np.where(terminated, code("terminated"), np.where(truncated, code("truncated"), code("cut"))).astype(np.int8)
        row = np.full(n, -1, np.int64)  # env -> its row of the chunk's ended envs (their final observations)
        row[np.asarray(result.ended, np.int64)] = np.arange(len(result.ended))
        decision_bytes = sum(buf[0, 0].nbytes for buf in self.bufs.values())
        per_part = max(1, PACKED_BYTES // max(1, decision_bytes * self.length))
        parts = [self._pack(emit[i:i + per_part], ends, row, result) for i in range(0, len(emit), per_part)]
        self.fill[emit] = 0
        return parts

    def _pack(self, emit: np.ndarray, ends: np.ndarray, row: np.ndarray, result: VectorChunk) -> SegmentBatch:
        """The segments of envs ``emit`` (their decisions copied out of the buffers once) as one message."""
        lengths = self.fill[emit]
        if int(lengths.min()) == int(lengths.max()):  # segments cut together (length, boundary)
            length, t = int(lengths[0]), len(emit) * int(lengths[0])
            every = len(emit) == len(self.env_ids)  # every env: a slice of the buffers, copied; else indexing copies
            fields = {name: (np.array(buf[:, :length]) if every else buf[emit, :length]).reshape(t, *buf.shape[2:])
                      for name, buf in self.bufs.items()}
        else:  # decision j of segment s is buffer row (emit[s], j)
            starts = np.cumsum(lengths) - lengths
            env_rows = np.repeat(emit, lengths)
            positions = np.arange(int(lengths.sum())) - np.repeat(starts, lengths)
            fields = {name: buf[env_rows, positions] for name, buf in self.bufs.items()}
        r = row[emit]
        ended = r >= 0
        last_obs = np.asarray(result.next_obs, np.float32)[emit]
        if ended.any():
            last_obs[ended] = result.final_obs[r[ended]]  # type: ignore[index]

        def pick(values: np.ndarray, empty: float) -> np.ndarray:  # per segment: its episode's, where one ended
            return np.where(ended, np.asarray(values)[np.where(ended, r, 0)], empty) if len(result.ended) else \
                np.full(len(emit), empty)

        return SegmentBatch(
            group=self.group, env_ids=self.env_ids[emit], episodes=self.episode[emit].copy(),
            lengths=lengths.astype(np.int32), ends=ends[emit], **fields, last_obs=last_obs,
            episode_offsets=self.offset[emit].copy(),
            episode_returns=pick(result.episode_return, 0.0).astype(np.float32),
            episode_lengths=pick(result.episode_length, -1).astype(np.int32),
            episode_successes=pick(result.episode_success, -1).astype(np.int8))


# A packed message's size, at most about (one segment more where one is larger): glibc allocates what is larger than
# its mmap threshold (up to 32 MiB) fresh from the kernel each time, and filling fresh pages cost more than the copy.
PACKED_BYTES = 8 << 20


DTYPES = {"obs": np.float32, "actions": np.float32, "latents": np.float32, "logprobs": np.float32,
          "values": np.float32, "rewards": np.float32, "steps": np.int32, "versions": np.int64}


class Episodes:
    """Each env's current episode index (the one it is in, or about to start).

    With groups of ``share`` envs (GRPO: envs ``g * share ... (g + 1) * share - 1`` start their episodes from
    the same states), group-mates run episode by episode together: an env that finished its episode waits
    at the start of the next one until every group-mate finished too, so every group of episodes completes.
    With ``share = 1`` every env always acts."""

    def __init__(self, env_ids: range, share: int = 1):
        self.share = share
        self.index = {env: 0 for env in env_ids}
        self._moved = asyncio.Event()

    def members(self, env: int) -> range:
        first = env // self.share * self.share
        return range(first, first + self.share)

    def may_act(self, env: int) -> bool:
        return self.share == 1 or self.index[env] <= min(self.index[m] for m in self.members(env))

    def set(self, env: int, index: int) -> None:
        if index != self.index[env]:
            self.index[env] = index
            self._moved.set()  # wake whoever waits for a group-mate
            self._moved = asyncio.Event()

    async def moved(self) -> None:
        """Return when any env's episode index changes."""
        await self._moved.wait()
