"""Trajectory assembly: one builder per environment turns chunk results into segments."""

from __future__ import annotations

import asyncio
from dataclasses import dataclass, field

import numpy as np

from ebrl.envs.worker import ChunkResult
from ebrl.messages import TrajectorySegment


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

    def __len__(self) -> int:
        return len(self._obs)

    def add(self, obs: np.ndarray, action: np.ndarray, latent: np.ndarray, logprob: float, value: float,
            version: int, result: ChunkResult, boundary: bool = False) -> TrajectorySegment | None:
        """Record one chunk decision and what the environment did; return a finished segment or None.
        ``boundary`` marks the last decision of an iteration: the segment is cut there so that every
        decision of the iteration reaches training."""
        if not self._obs:
            self._episode = result.episode
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
        )
        for buf in (self._obs, self._actions, self._latents, self._logprobs, self._values, self._rewards, self._steps,
                    self._versions, self._returns, self._lengths, self._successes):
            buf.clear()
        return segment


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
