"""The rollout's messages: observations (sim -> gen), action chunks (gen -> sim) and the finished segments
training learns from (sim -> train), one per env or packed for a group."""

from __future__ import annotations

import math
from dataclasses import dataclass
from typing import Annotated, Literal

import numpy as np

from ebrl.messages.common import (DATA_MAX_BYTES, MAX_VERSION, NO_BYTES, MessageError, all_finite, byte_rows, doc,
                                  in_range)
from ebrl.typecheck import Array


@dataclass
class Observation:
    """Observations of one environment group at a chunk boundary (sim -> gen)."""

    KEY = "ebrl/data/<run>/obs/<group>"
    group: int = doc("group index")
    seq: int = doc("chunk counter of this group; the action chunk answering it carries the same seq")
    env_ids: Annotated[np.ndarray, Array("int64", 1)] = doc("global env ids, shape [E]")
    obs: Annotated[np.ndarray, Array("float32")] = doc(
        "observations, shape [E, *obs_shape]; with `images`, the fields that are not bytes, shape [E, n]")
    sent_at: float = doc("epoch seconds when sim published it")
    images: Annotated[np.ndarray, Array("uint8", 2)] = doc(
        "the observation layout's uint8 fields (camera images) as bytes, shape [E, byte_size] "
        "(ObsLayout.to_wire); shape [E, 0] or [0, 0] when it has none", default_factory=lambda: NO_BYTES.copy())

    MAX_BYTES = DATA_MAX_BYTES

    def check(self) -> None:
        in_range("Observation.group", self.group, 0, 1 << 20)
        in_range("Observation.seq", self.seq)
        if self.obs.ndim < 1 or not 0 < len(self.env_ids) == len(self.obs):
            raise MessageError(f"Observation: {len(self.env_ids)} env ids for observations of shape {self.obs.shape}")
        if len(self.env_ids) and int(self.env_ids.min()) < 0:
            raise MessageError("Observation.env_ids: a negative env id")
        byte_rows("Observation.images", self.images, len(self.obs))


@dataclass
class ActionChunk:
    """An action chunk for every env of one group (gen -> sim)."""

    KEY = "ebrl/data/<run>/act/<group>"
    group: int = doc("group index")
    seq: int = doc("seq of the observation this answers")
    policy_version: int = doc("version of the weights that produced these actions")
    actions: Annotated[np.ndarray, Array("float32", 3)] = doc("actions, shape [E, K, action_dim]")
    logprobs: Annotated[np.ndarray, Array("float32", 1)] = doc("log-probability of each whole chunk, shape [E]")
    values: Annotated[np.ndarray, Array("float32", 1)] = doc("value estimate at the observation, shape [E]")
    latents: Annotated[np.ndarray, Array("float32")] = doc(
        "the policy's sampling state that training needs to recompute the exact log-prob (flow policies: the "
        "initial noise), shape [E, *latent_shape]; [E, 0] for Gaussian policies")

    MAX_BYTES = DATA_MAX_BYTES

    def check(self) -> None:
        in_range("ActionChunk.group", self.group, 0, 1 << 20)
        in_range("ActionChunk.seq", self.seq)
        in_range("ActionChunk.policy_version", self.policy_version)
        n = len(self.actions)
        if not 0 < n == len(self.logprobs) == len(self.values) == len(self.latents):
            raise MessageError(f"ActionChunk: actions, logprobs, values and latents differ in length ({n}, "
                               f"{len(self.logprobs)}, {len(self.values)}, {len(self.latents)})")
        all_finite("ActionChunk", self.actions, self.logprobs, self.values, self.latents)


@dataclass
class TrajectorySegment:
    """A finished piece of one environment's trajectory, T chunk decisions long (sim -> train)."""

    KEY = "ebrl/data/<run>/traj/<group>"
    group: int = doc("group index")
    env_id: int = doc("global env id")
    episode: int = doc("index of the env's episode this segment belongs to, from 0 (a segment never spans two)")
    obs: Annotated[np.ndarray, Array("float32")] = doc("observation before each chunk, shape [T, *obs_shape]")
    actions: Annotated[np.ndarray, Array("float32", 3)] = doc("chunks sent, shape [T, K, action_dim]")
    latents: Annotated[np.ndarray, Array("float32")] = doc("policy sampling state of each chunk, shape [T, *latent_shape]")
    logprobs: Annotated[np.ndarray, Array("float32", 1)] = doc("behaviour log-prob of each chunk, shape [T]")
    values: Annotated[np.ndarray, Array("float32", 1)] = doc("value estimate at each chunk start, shape [T]")
    rewards: Annotated[np.ndarray, Array("float32", 1)] = doc("sum of env rewards over each chunk, shape [T]")
    steps: Annotated[np.ndarray, Array("int32", 1)] = doc("env steps executed in each chunk (< K if the episode ended), shape [T]")
    versions: Annotated[np.ndarray, Array("int64", 1)] = doc("policy version that produced each chunk, shape [T]")
    end: Literal["terminated", "truncated", "cut"] = doc(
        "why the segment ended: terminal state (no bootstrap), time limit or segment length (bootstrap from last_obs)"
    )
    last_obs: Annotated[np.ndarray, Array("float32")] = doc("observation after the last chunk, for bootstrapping")
    episode_returns: list[float] = doc("returns of episodes that finished inside this segment")
    episode_lengths: list[int] = doc("lengths (env steps) of episodes that finished inside this segment")
    episode_successes: list[bool | None] = doc(
        "the task's success check at the end of each of those episodes (null where the task has none); empty: "
        "not reported", default_factory=list)
    episode_offset: int = doc(
        "env steps of its episode before this segment's first decision (0: the segment starts the episode; -1: "
        "not reported). Training follows each env's episode by it and computes returns itself", default=-1)
    images: Annotated[np.ndarray, Array("uint8", 2)] = doc(
        "the uint8 fields of `obs` as bytes, shape [T, byte_size] (as Observation.images; `obs` and `last_obs` "
        "then hold the other fields); [0, 0] when the layout has none", default_factory=lambda: NO_BYTES.copy())
    last_images: Annotated[np.ndarray, Array("uint8", 1)] = doc(
        "the uint8 fields of `last_obs` as bytes, shape [byte_size]", default_factory=lambda: np.zeros(0, np.uint8))

    MAX_BYTES = DATA_MAX_BYTES

    def check(self) -> None:
        """Every per-decision field is T long and every value finite; counts and versions in range."""
        name = "TrajectorySegment"
        in_range(f"{name}.group", self.group, 0, 1 << 20)
        in_range(f"{name}.env_id", self.env_id, 0, 1 << 30)
        in_range(f"{name}.episode", self.episode)
        t = len(self.obs)
        lengths = [len(getattr(self, f)) for f in ("actions", "latents", "logprobs", "values", "rewards", "steps",
                                                   "versions")]
        if self.obs.ndim < 1 or t == 0 or any(n != t for n in lengths):
            raise MessageError(f"{name}: per-decision fields differ in length (obs {t}; actions, latents, "
                               f"logprobs, values, rewards, steps, versions {lengths})")
        if self.last_obs.shape != self.obs.shape[1:]:
            raise MessageError(f"{name}.last_obs has shape {self.last_obs.shape}, observations {self.obs.shape[1:]}")
        byte_rows(f"{name}.images", self.images, t)
        if self.images.size and self.last_images.shape != self.images.shape[1:] or (
                not self.images.size and self.last_images.size):
            raise MessageError(f"{name}.last_images has shape {self.last_images.shape}, images {self.images.shape}")
        all_finite(name, self.obs, self.actions, self.latents, self.logprobs, self.values, self.rewards, self.last_obs)
        if int(self.steps.min()) < 0 or int(self.steps.max()) > self.actions.shape[1]:
            raise MessageError(f"{name}.steps: outside 0..{self.actions.shape[1]} (the chunk length)")
        if int(self.versions.min()) < 0 or int(self.versions.max()) > MAX_VERSION:
            raise MessageError(f"{name}.versions: a version outside [0, {MAX_VERSION}]")
        if len(self.episode_returns) != len(self.episode_lengths) or len(self.episode_returns) > t * (
                self.actions.shape[1] + 1):
            raise MessageError(f"{name}: {len(self.episode_returns)} episode returns, {len(self.episode_lengths)} "
                               "lengths")
        if not all(math.isfinite(r) for r in self.episode_returns) or any(n < 0 for n in self.episode_lengths):
            raise MessageError(f"{name}: an episode return that is not finite or a negative length")
        if self.episode_successes and len(self.episode_successes) != len(self.episode_returns):
            raise MessageError(f"{name}: {len(self.episode_successes)} episode successes, "
                               f"{len(self.episode_returns)} returns")
        in_range(f"{name}.episode_offset", self.episode_offset, -1, 1 << 40)


SEGMENT_ENDS: tuple[str, ...] = ("cut", "terminated", "truncated")  # SegmentBatch.ends codes, as TrajectorySegment.end


@dataclass
class SegmentBatch:
    """Finished segments of many environments of one group, packed (sim -> train): what a vectorized group of
    hundreds or thousands of envs publishes at a chunk instead of a :class:`TrajectorySegment` per env. Segment
    ``s`` is env ``env_ids[s]``'s decisions ``offsets[s] .. offsets[s] + lengths[s]`` of the per-decision fields
    (``offsets``: the running sum of ``lengths``); it means exactly what the same TrajectorySegment would."""

    KEY = "ebrl/data/<run>/traj/<group>/packed"
    group: int = doc("group index")
    env_ids: Annotated[np.ndarray, Array("int64", 1)] = doc("global env id of each segment, shape [S]")
    episodes: Annotated[np.ndarray, Array("int64", 1)] = doc("episode index of each segment's env, shape [S]")
    lengths: Annotated[np.ndarray, Array("int32", 1)] = doc("decisions of each segment (>= 1), shape [S]; sum T")
    ends: Annotated[np.ndarray, Array("int8", 1)] = doc(
        "why each segment ended, shape [S]: 0 cut (segment length or iteration boundary), 1 terminated, "
        "2 truncated (TrajectorySegment.end)")
    obs: Annotated[np.ndarray, Array("float32")] = doc(
        "observation before each chunk, segments one after another, shape [T, *obs_shape]")
    actions: Annotated[np.ndarray, Array("float32", 3)] = doc("chunks sent, shape [T, K, action_dim]")
    latents: Annotated[np.ndarray, Array("float32")] = doc("policy sampling state of each chunk, shape [T, *latent_shape]")
    logprobs: Annotated[np.ndarray, Array("float32", 1)] = doc("behaviour log-prob of each chunk, shape [T]")
    values: Annotated[np.ndarray, Array("float32", 1)] = doc("value estimate at each chunk start, shape [T]")
    rewards: Annotated[np.ndarray, Array("float32", 1)] = doc("sum of env rewards over each chunk, shape [T]")
    steps: Annotated[np.ndarray, Array("int32", 1)] = doc("env steps executed in each chunk, shape [T]")
    versions: Annotated[np.ndarray, Array("int64", 1)] = doc("policy version that produced each chunk, shape [T]")
    last_obs: Annotated[np.ndarray, Array("float32")] = doc(
        "observation after each segment's last chunk, for bootstrapping, shape [S, *obs_shape]")
    episode_offsets: Annotated[np.ndarray, Array("int64", 1)] = doc(
        "env steps of each segment's episode before its first decision, shape [S] (0: it starts the episode; "
        "TrajectorySegment.episode_offset)")
    episode_returns: Annotated[np.ndarray, Array("float32", 1)] = doc(
        "return of the episode that ended at a segment's last decision, shape [S] (0 where none did)")
    episode_lengths: Annotated[np.ndarray, Array("int32", 1)] = doc(
        "its length in env steps, shape [S]; -1 where no episode ended in the segment")
    episode_successes: Annotated[np.ndarray, Array("int8", 1)] = doc(
        "its success check, shape [S]: 1, 0, or -1 where none ended or the task reports none")
    images: Annotated[np.ndarray, Array("uint8", 2)] = doc(
        "the uint8 fields of `obs` as bytes, shape [T, byte_size] (as TrajectorySegment.images); [0, 0] when the "
        "layout has none", default_factory=lambda: NO_BYTES.copy())
    last_images: Annotated[np.ndarray, Array("uint8", 2)] = doc(
        "the uint8 fields of `last_obs` as bytes, shape [S, byte_size]; [0, 0] when the layout has none",
        default_factory=lambda: NO_BYTES.copy())

    MAX_BYTES = DATA_MAX_BYTES

    def check(self) -> None:
        """Per-segment fields S long, per-decision fields T = sum(lengths) long, every value finite, counts,
        codes and versions in range."""
        name = "SegmentBatch"
        in_range(f"{name}.group", self.group, 0, 1 << 20)
        s = len(self.env_ids)
        per_segment = [len(getattr(self, f)) for f in ("episodes", "lengths", "ends", "last_obs", "episode_offsets",
                                                       "episode_returns", "episode_lengths", "episode_successes")]
        if s == 0 or any(n != s for n in per_segment):
            raise MessageError(f"{name}: per-segment fields differ in length (env_ids {s}; {per_segment})")
        if int(self.lengths.min()) < 1:
            raise MessageError(f"{name}.lengths: a segment without decisions")
        t = int(self.lengths.sum(dtype=np.int64))
        per_decision = [len(getattr(self, f)) for f in ("obs", "actions", "latents", "logprobs", "values", "rewards",
                                                        "steps", "versions")]
        if self.obs.ndim < 1 or any(n != t for n in per_decision):
            raise MessageError(f"{name}: per-decision fields differ from sum(lengths) = {t} ({per_decision})")
        if self.last_obs.shape[1:] != self.obs.shape[1:]:
            raise MessageError(f"{name}.last_obs has shape {self.last_obs.shape}, observations {self.obs.shape}")
        byte_rows(f"{name}.images", self.images, t)
        byte_rows(f"{name}.last_images", self.last_images, s)
        if bool(self.images.size) != bool(self.last_images.size) or (
                self.images.size and self.images.shape[1] != self.last_images.shape[1]):
            raise MessageError(f"{name}.last_images has shape {self.last_images.shape}, images {self.images.shape}")
        all_finite(name, self.obs, self.actions, self.latents, self.logprobs, self.values, self.rewards, self.last_obs,
                self.episode_returns)
        for field_name, values, low, high in (
                ("env_ids", self.env_ids, 0, 1 << 30), ("episodes", self.episodes, 0, MAX_VERSION),
                ("ends", self.ends, 0, len(SEGMENT_ENDS) - 1), ("steps", self.steps, 0, self.actions.shape[1]),
                ("episode_offsets", self.episode_offsets, -1, 1 << 40),
                ("versions", self.versions, 0, MAX_VERSION), ("episode_lengths", self.episode_lengths, -1, 1 << 30),
                ("episode_successes", self.episode_successes, -1, 1)):
            if values.size and (int(values.min()) < low or int(values.max()) > high):
                raise MessageError(f"{name}.{field_name}: a value outside [{low}, {high}]")
        if len(np.unique(self.env_ids)) != s:  # one chunk's segments: at most one per env
            raise MessageError(f"{name}.env_ids: an env twice in one batch")

    def segments(self) -> list[TrajectorySegment]:
        """The TrajectorySegment of each packed segment, in order (views of this message's arrays; checked as
        this message was, so not again)."""
        ends = np.cumsum(self.lengths, dtype=np.int64)
        starts = ends - self.lengths
        out = []
        pixels = bool(self.images.size)
        rows = zip(starts.tolist(), ends.tolist(), self.env_ids.tolist(), self.episodes.tolist(), self.ends.tolist(),
                   self.episode_returns.tolist(), self.episode_lengths.tolist(), self.episode_successes.tolist(),
                   self.episode_offsets.tolist())
        for s, (a, b, env, episode, end, ret, length, success, offset) in enumerate(rows):
            ended = length >= 0
            out.append(TrajectorySegment(
                group=self.group, env_id=env, episode=episode, obs=self.obs[a:b], actions=self.actions[a:b],
                latents=self.latents[a:b], logprobs=self.logprobs[a:b], values=self.values[a:b],
                rewards=self.rewards[a:b], steps=self.steps[a:b], versions=self.versions[a:b],
                end=SEGMENT_ENDS[end], last_obs=self.last_obs[s],  # type: ignore[arg-type]
                episode_returns=[ret] if ended else [], episode_lengths=[length] if ended else [],
                episode_successes=([None if success < 0 else bool(success)] if ended else []), episode_offset=offset,
                images=self.images[a:b] if pixels else NO_BYTES.copy(),
                last_images=self.last_images[s] if pixels else np.zeros(0, np.uint8)))
        return out
