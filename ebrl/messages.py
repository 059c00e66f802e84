"""Every message on the EBRL bus, defined once; ``schemas/`` is generated from here.

A message is a dataclass whose fields carry a docstring (``doc``). On receipt :func:`decode_message`
checks, in this order, and raises :class:`MessageError` (services count it and drop the message):

1. the payload's size against the type's ``MAX_BYTES``, before anything is decoded
   (:class:`OversizedError`; a weights part, a segment and a stats report have different limits);
2. the msgpack and array headers (:mod:`ebrl.codec`: bounded lengths, exact byte counts);
3. every field's type (:mod:`ebrl.typecheck`);
4. the message's meaning (its ``check`` method): per-decision fields of one length, finite values, counts
   and versions in range.

What only the receiver knows (the policy's shapes, the weights' layout, which instances exist) it checks
itself. On the wire a message is a msgpack map of its fields plus ``"v"`` (the schema version); arrays
travel through :mod:`ebrl.codec`.
"""

from __future__ import annotations

import dataclasses
import json
import math
import re
import types
import typing
from dataclasses import dataclass, field
from typing import Annotated, Any, Literal, TypeVar, get_args, get_origin

import numpy as np

from ebrl import codec, keys
from ebrl import typecheck
from ebrl.typecheck import Array

SCHEMA_VERSION = 1

T = TypeVar("T")


class MessageError(ValueError):
    """A payload that is not a valid message of the expected type."""


class OversizedError(MessageError):
    """A payload over its message type's ``MAX_BYTES`` (counted as ``bus/oversized`` too)."""


KIB, MIB = 1 << 10, 1 << 20
CONTROL_MAX_BYTES = 64 * KIB  # stop, affinity, quota, GPU share: a few fields
DATA_MAX_BYTES = 256 * MIB  # a group's observations or one segment: camera images of many envs or steps
MAX_VERSION = 1 << 53  # policy and control versions beyond this are not counters (float64 loses them)
MAX_METRICS = 4096  # names in one stats report
MAX_TEXT = 4096  # characters of a free-text field (a reason, an event line)


def _finite(name: str, *arrays: np.ndarray) -> None:
    for array in arrays:
        if array.dtype.kind == "f" and array.size and not np.isfinite(array).all():
            raise MessageError(f"{name}: a value is not finite (NaN or inf)")


def _count(name: str, value: int, low: int = 0, high: int = MAX_VERSION) -> None:
    if not low <= value <= high:
        raise MessageError(f"{name} = {value}: outside [{low}, {high}]")


_NO_BYTES = np.zeros((0, 0), np.uint8)  # a message's ``images`` when the observations have no uint8 fields


def _bytes_rows(name: str, images: np.ndarray, rows: int) -> None:
    """An ``images`` array holds a row per observation, or nothing at all."""
    if images.size and images.shape[0] != rows:
        raise MessageError(f"{name}: {images.shape[0]} rows of bytes for {rows} observations")


def doc(text: str, **kw: Any) -> Any:
    """A dataclass field with a docstring (used in ``schemas/`` and docs/reference/messages.md)."""
    return field(metadata={"doc": text}, **kw)


F32 = Annotated[np.ndarray, Array("float32")]


# --- data ------------------------------------------------------------------------


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
        "(ObsLayout.to_wire); shape [E, 0] or [0, 0] when it has none", default_factory=lambda: _NO_BYTES.copy())

    MAX_BYTES = DATA_MAX_BYTES

    def check(self) -> None:
        _count("Observation.group", self.group, 0, 1 << 20)
        _count("Observation.seq", self.seq)
        if self.obs.ndim < 1 or not 0 < len(self.env_ids) == len(self.obs):
            raise MessageError(f"Observation: {len(self.env_ids)} env ids for observations of shape {self.obs.shape}")
        if len(self.env_ids) and int(self.env_ids.min()) < 0:
            raise MessageError("Observation.env_ids: a negative env id")
        _bytes_rows("Observation.images", self.images, len(self.obs))


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
        _count("ActionChunk.group", self.group, 0, 1 << 20)
        _count("ActionChunk.seq", self.seq)
        _count("ActionChunk.policy_version", self.policy_version)
        n = len(self.actions)
        if not 0 < n == len(self.logprobs) == len(self.values) == len(self.latents):
            raise MessageError(f"ActionChunk: actions, logprobs, values and latents differ in length ({n}, "
                               f"{len(self.logprobs)}, {len(self.values)}, {len(self.latents)})")
        _finite("ActionChunk", self.actions, self.logprobs, self.values, self.latents)


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
        "then hold the other fields); [0, 0] when the layout has none", default_factory=lambda: _NO_BYTES.copy())
    last_images: Annotated[np.ndarray, Array("uint8", 1)] = doc(
        "the uint8 fields of `last_obs` as bytes, shape [byte_size]", default_factory=lambda: np.zeros(0, np.uint8))

    MAX_BYTES = DATA_MAX_BYTES

    def check(self) -> None:
        """Every per-decision field is T long and every value finite; counts and versions in range."""
        name = "TrajectorySegment"
        _count(f"{name}.group", self.group, 0, 1 << 20)
        _count(f"{name}.env_id", self.env_id, 0, 1 << 30)
        _count(f"{name}.episode", self.episode)
        t = len(self.obs)
        lengths = [len(getattr(self, f)) for f in ("actions", "latents", "logprobs", "values", "rewards", "steps",
                                                   "versions")]
        if self.obs.ndim < 1 or t == 0 or any(n != t for n in lengths):
            raise MessageError(f"{name}: per-decision fields differ in length (obs {t}; actions, latents, "
                               f"logprobs, values, rewards, steps, versions {lengths})")
        if self.last_obs.shape != self.obs.shape[1:]:
            raise MessageError(f"{name}.last_obs has shape {self.last_obs.shape}, observations {self.obs.shape[1:]}")
        _bytes_rows(f"{name}.images", self.images, t)
        if self.images.size and self.last_images.shape != self.images.shape[1:] or (
                not self.images.size and self.last_images.size):
            raise MessageError(f"{name}.last_images has shape {self.last_images.shape}, images {self.images.shape}")
        _finite(name, self.obs, self.actions, self.latents, self.logprobs, self.values, self.rewards, self.last_obs)
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
        _count(f"{name}.episode_offset", self.episode_offset, -1, 1 << 40)


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
        "layout has none", default_factory=lambda: _NO_BYTES.copy())
    last_images: Annotated[np.ndarray, Array("uint8", 2)] = doc(
        "the uint8 fields of `last_obs` as bytes, shape [S, byte_size]; [0, 0] when the layout has none",
        default_factory=lambda: _NO_BYTES.copy())

    MAX_BYTES = DATA_MAX_BYTES

    def check(self) -> None:
        """Per-segment fields S long, per-decision fields T = sum(lengths) long, every value finite, counts,
        codes and versions in range."""
        name = "SegmentBatch"
        _count(f"{name}.group", self.group, 0, 1 << 20)
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
        _bytes_rows(f"{name}.images", self.images, t)
        _bytes_rows(f"{name}.last_images", self.last_images, s)
        if bool(self.images.size) != bool(self.last_images.size) or (
                self.images.size and self.images.shape[1] != self.last_images.shape[1]):
            raise MessageError(f"{name}.last_images has shape {self.last_images.shape}, images {self.images.shape}")
        _finite(name, self.obs, self.actions, self.latents, self.logprobs, self.values, self.rewards, self.last_obs,
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
                images=self.images[a:b] if pixels else _NO_BYTES.copy(),
                last_images=self.last_images[s] if pixels else np.zeros(0, np.uint8)))
        return out


TRANSITION_FIELDS = ("obs", "actions", "rewards", "steps", "terminal", "next_obs", "versions")


def _transitions(name: str, msg: Any) -> None:
    """Transitions of a replay message: every field one row per transition, observations of one shape, every
    value finite, steps and versions in range."""
    n = len(msg.rewards)
    lengths = [len(getattr(msg, f)) for f in TRANSITION_FIELDS]
    if any(k != n for k in lengths):
        raise MessageError(f"{name}: transition fields differ in length ({dict(zip(TRANSITION_FIELDS, lengths))})")
    if msg.next_obs.shape != msg.obs.shape:
        raise MessageError(f"{name}.next_obs has shape {msg.next_obs.shape}, obs {msg.obs.shape}")
    _finite(name, msg.obs, msg.actions, msg.rewards, msg.next_obs)
    if n and (int(msg.steps.min()) < 0 or int(msg.steps.max()) > 1 << 20):
        raise MessageError(f"{name}.steps: a chunk of fewer than 0 or absurdly many env steps")
    if n and (int(msg.versions.min()) < 0 or int(msg.versions.max()) > MAX_VERSION):
        raise MessageError(f"{name}.versions: a version outside [0, {MAX_VERSION}]")
    if n and int(msg.terminal.max()) > 1:
        raise MessageError(f"{name}.terminal: a flag other than 0 or 1")


@dataclass
class ReplayRequest:
    """New transitions for the replay, and the minibatches training wants next (train -> replay). An update's
    first request carries the decisions it took in; the ones after it only ask for more minibatches."""

    KEY = "ebrl/data/<run>/replay/request"
    session: int = doc("random, fixed for one training process: with seq, tells a request sent again (its "
                       "transitions are not added twice) from a new one")
    seq: int = doc("increases by one per request of this session")
    acked: int = doc("transitions the replay had taken in (ReplaySample.inserted) by its last answer to training: "
                     "a restarted replay counts what it no longer has as lost (replay/lost)")
    batches: int = doc("minibatches wanted after the new transitions are in")
    batch_size: int = doc("transitions per minibatch")
    obs: Annotated[np.ndarray, Array("float32", 2)] = doc("observation before each decision, shape [N, obs_size]")
    actions: Annotated[np.ndarray, Array("float32", 2)] = doc("the chunk as the env got it, flat, shape [N, K*A]")
    rewards: Annotated[np.ndarray, Array("float32", 1)] = doc("the chunk's reward (its steps' sum), shape [N]")
    steps: Annotated[np.ndarray, Array("int32", 1)] = doc("env steps the chunk ran, shape [N]")
    terminal: Annotated[np.ndarray, Array("uint8", 1)] = doc("1 where the episode terminated after it (no "
                                                              "bootstrap), shape [N]")
    next_obs: Annotated[np.ndarray, Array("float32", 2)] = doc("observation after the chunk, shape [N, obs_size]")
    versions: Annotated[np.ndarray, Array("int64", 1)] = doc("policy version that acted, shape [N]")

    MAX_BYTES = DATA_MAX_BYTES

    def check(self) -> None:
        _count("ReplayRequest.seq", self.seq)
        _count("ReplayRequest.session", self.session, 0, (1 << 63) - 1)
        _count("ReplayRequest.acked", self.acked, 0, (1 << 62))
        _count("ReplayRequest.batches", self.batches, 0, 1 << 16)
        _count("ReplayRequest.batch_size", self.batch_size, 1, 1 << 24)
        _transitions("ReplayRequest", self)


@dataclass
class ReplaySample:
    """Minibatches drawn uniformly from the replay, one after another, answering one request (replay -> train)."""

    KEY = "ebrl/data/<run>/replay/sample"
    session: int = doc("the request's session")
    seq: int = doc("the request's seq")
    size: int = doc("transitions the replay holds")
    inserted: int = doc("transitions it has taken in since it began (also those overwritten since), restored "
                        "with its contents after a restart")
    obs: Annotated[np.ndarray, Array("float32", 2)] = doc("shape [batches * batch_size, obs_size]; none where the "
                                                          "replay holds nothing")
    actions: Annotated[np.ndarray, Array("float32", 2)] = doc("shape [batches * batch_size, K*A]")
    rewards: Annotated[np.ndarray, Array("float32", 1)] = doc("shape [batches * batch_size]")
    steps: Annotated[np.ndarray, Array("int32", 1)] = doc("shape [batches * batch_size]")
    terminal: Annotated[np.ndarray, Array("uint8", 1)] = doc("shape [batches * batch_size]")
    next_obs: Annotated[np.ndarray, Array("float32", 2)] = doc("shape [batches * batch_size, obs_size]")
    versions: Annotated[np.ndarray, Array("int64", 1)] = doc("shape [batches * batch_size]")

    MAX_BYTES = DATA_MAX_BYTES

    def check(self) -> None:
        _count("ReplaySample.seq", self.seq)
        _count("ReplaySample.session", self.session, 0, (1 << 63) - 1)
        _count("ReplaySample.size", self.size, 0, 1 << 40)
        _count("ReplaySample.inserted", self.inserted, 0, 1 << 62)
        _transitions("ReplaySample", self)


@dataclass
class Weights:
    """Versioned policy weights (train -> gen)."""

    KEY = "ebrl/data/<run>/weights"
    version: int = doc("policy version; increases by one per update")
    params: dict[str, Annotated[np.ndarray, Array()]] = doc("state dict: parameter name -> array")
    created_at: float = doc("epoch seconds when train produced them")

    MAX_BYTES = 8 * MIB  # ebrl.weights sends a version of 4 MiB or more in parts

    def check(self) -> None:
        _count("Weights.version", self.version)
        _finite("Weights.params", *self.params.values())


@dataclass
class WeightsPart:
    """One part of a large weights version (train -> gen): a byte range of the version's arrays laid end to end,
    each array at a 64-byte aligned offset. Part ``index`` starts at ``index * part_bytes``; part 0 carries the
    manifest (names, dtypes, shapes, offsets). A receiver applies a version only once every part arrived."""

    KEY = "ebrl/data/<run>/weights/parts"
    version: int = doc("policy version; increases by one per update")
    index: int = doc("part number, 0 .. count - 1")
    count: int = doc("number of parts of this version")
    part_bytes: int = doc("length of every part but the last, which holds the rest")
    total_bytes: int = doc("length of the version's buffer")
    created_at: float = doc("epoch seconds when train produced the weights")
    data: Annotated[np.ndarray, Array("uint8", 1)] = doc("this part's bytes")
    names: list[str] = doc("part 0: parameter names, in buffer order; other parts: empty", default_factory=list)
    dtypes: list[str] = doc("part 0: numpy dtype string of each parameter (e.g. '<f4')", default_factory=list)
    shapes: list[list[int]] = doc("part 0: shape of each parameter", default_factory=list)
    offsets: list[int] = doc("part 0: byte offset of each parameter in the buffer", default_factory=list)

    MAX_BYTES = 8 * MIB  # ebrl.weights.PART_BYTES of data and part 0's manifest

    def check(self) -> None:
        _count("WeightsPart.version", self.version)
        _count("WeightsPart.count", self.count, 1, 1 << 20)
        _count("WeightsPart.index", self.index, 0, self.count - 1)
        _count("WeightsPart.part_bytes", self.part_bytes, 1, 64 * MIB)
        _count("WeightsPart.total_bytes", self.total_bytes, 1, 1 << 40)


# --- observability -----------------------------------------------------------------


@dataclass
class StatsReport:
    """Periodic stats of one service instance, published every `stats_interval` seconds."""

    KEY = "ebrl/stats/<run>/<service>/<instance>"
    run: str = doc("run name")
    service: str = doc("service role: sim, gen, train, ...")
    instance: int = doc("instance index of the service")
    time: float = doc("epoch seconds of the report")
    seq: int = doc("report counter of this instance, from 0")
    metrics: dict[str, float] = doc("namespaced metrics, e.g. sim/env_steps_per_s (see docs/stats.md)")

    MAX_BYTES = 1 * MIB

    def check(self) -> None:
        _count("StatsReport.instance", self.instance, 0, 1 << 20)
        if len(self.metrics) > MAX_METRICS:
            raise MessageError(f"StatsReport: {len(self.metrics)} metrics, more than {MAX_METRICS}")


@dataclass
class SpanBatch:
    """Timeline spans of one lane, batched (a service publishes each lane every 0.2 s): span i was busy
    with ``label[i]`` from ``start[i]`` to ``end[i]``."""

    KEY = "ebrl/stats/<run>/spans/<lane>"
    lane: str = doc("timeline lane, e.g. sim.g0, gen, train, weights")
    service: str = doc("service role that recorded the spans")
    instance: int = doc("instance index of that service")
    start: list[float] = doc("epoch seconds, one per span")
    end: list[float] = doc("epoch seconds, one per span")
    label: list[str] = doc("what ran, one per span: chunk, wait, forward, update, v<version>")

    MAX_BYTES = 1 * MIB  # at most SPAN_BATCH_MAX spans, about 120 KB

    def __post_init__(self) -> None:
        if not len(self.start) == len(self.end) == len(self.label):
            raise MessageError(f"SpanBatch: start, end and label differ in length "
                               f"({len(self.start)}, {len(self.end)}, {len(self.label)})")

    def spans(self) -> list["Span"]:
        return [Span(self.lane, a, b, label, self.service, self.instance)
                for a, b, label in zip(self.start, self.end, self.label)]


@dataclass
class Span:
    """One span of a :class:`SpanBatch`, as readers use it (not a wire message of its own)."""

    lane: str
    start: float
    end: float
    label: str
    service: str
    instance: int


@dataclass
class Event:
    """Something worth a line in the run's event log: a service came up, re-allocation, restart, ..."""

    KEY = "ebrl/stats/<run>/events/<service>"
    time: float = doc("epoch seconds")
    service: str = doc("service role that reports it")
    instance: int = doc("instance index of that service")
    kind: str = doc("short machine-readable kind, e.g. live, exited, quota, affinity, realloc")
    text: str = doc("one human-readable line")

    MAX_BYTES = 256 * KIB


RETURN_WINDOW = 20  # the latest episodes behind a reported mean return or success rate (sim's, train's)
EPISODES_MAX = 1024  # most records in one EpisodeBatch; a simulator finishing more per interval counts the rest


@dataclass
class EpisodeBatch:
    """Every episode one simulator instance finished since its previous batch, one record each (sim -> anyone):
    the per-episode returns and successes behind ``sim/episode_return_mean`` and ``sim/success_rate``. Published
    with the instance's stats report, at most ``EPISODES_MAX`` records (the oldest beyond are dropped and
    counted as ``sim/episode_records_dropped``); the lists are parallel, one entry per episode."""

    KEY = "ebrl/stats/<run>/episodes/<service>"
    service: str = doc("service role that ran the episodes (sim)")
    instance: int = doc("instance index of that service (the host's number)")
    env_id: list[int] = doc("global env id")
    episode: list[int] = doc("index of the episode among that env's, from 0")
    returns: list[float] = doc("undiscounted return of the episode")
    length: list[int] = doc("env steps of the episode")
    success: list[bool | None] = doc("the task's success check at the episode's end; null where the task has none")
    policy_version: list[int] = doc("policy version of the chunk that ended the episode")
    env_steps: list[int] = doc("env steps this instance had run when the episode ended (its sim/env_steps)")
    end_time: list[float] = doc("epoch seconds when the episode ended")

    MAX_BYTES = 1 * MIB

    def __post_init__(self) -> None:
        lengths = {len(getattr(self, f)) for f in ("env_id", "episode", "returns", "length", "success",
                                                    "policy_version", "env_steps", "end_time")}
        if len(lengths) != 1:
            raise MessageError("EpisodeBatch: the per-episode lists differ in length")
        if lengths.pop() > EPISODES_MAX:
            raise MessageError(f"EpisodeBatch: more than {EPISODES_MAX} episodes")


# --- control -----------------------------------------------------------------------


@dataclass
class Stop:
    """Ask a service to stop gracefully."""

    KEY = "ebrl/ctl/<run>/<service>/<instance>/stop"
    reason: str = doc("why, for the log")

    MAX_BYTES = CONTROL_MAX_BYTES

    def check(self) -> None:
        if len(self.reason) > MAX_TEXT:
            raise MessageError(f"Stop.reason: {len(self.reason)} characters, more than {MAX_TEXT}")


@dataclass
class Affinity:
    """Pin a service's process (and the workers it owns) to CPU cores."""

    KEY = "ebrl/ctl/<run>/<service>/<instance>/affinity"
    version: int = doc("monotonic; an update with a version already applied is ignored")
    cores: list[int] = doc("CPU core ids")

    MAX_BYTES = CONTROL_MAX_BYTES

    def check(self) -> None:
        _count("Affinity.version", self.version)
        if not self.cores or len(set(self.cores)) != len(self.cores) or not all(0 <= c < 1 << 16 for c in self.cores):
            raise MessageError(f"Affinity.cores = {self.cores[:8]}: expected distinct core ids, at least one")


@dataclass
class Quota:
    """Resource quota of a service: thread count and GPU share."""

    KEY = "ebrl/ctl/<run>/<service>/<instance>/quota"
    version: int = doc("monotonic; an update with a version already applied is ignored")
    threads: int | None = doc("torch intra-op threads", default=None)
    sm_percent: float | None = doc("GPU SM share in percent", default=None)
    mem_bytes: int | None = doc("GPU memory budget in bytes", default=None)
    batch: int | None = doc("batch size the stage should use (gen: most envs per forward pass)", default=None)

    MAX_BYTES = CONTROL_MAX_BYTES

    def check(self) -> None:
        _count("Quota.version", self.version)
        if self.threads is not None:
            _count("Quota.threads", self.threads, 1, 4096)
        if self.sm_percent is not None and not 0 < self.sm_percent <= 100:
            raise MessageError(f"Quota.sm_percent = {self.sm_percent}: outside (0, 100]")
        if self.mem_bytes is not None:
            _count("Quota.mem_bytes", self.mem_bytes, 0, 1 << 50)
        if self.batch is not None:
            _count("Quota.batch", self.batch, 1, 1 << 24)


# The variables of a GPU share (ebrl.resources.pool.Binding.env), each with the values it may take: devices by
# index or UUID, an SM percentage, MPS's per-device memory limits ("0=1024M").
GPU_SHARE_VARIABLES = {
    "CUDA_VISIBLE_DEVICES": r"(\d{1,3}|(GPU|MIG)-[0-9A-Za-z/-]{1,80})(,(\d{1,3}|(GPU|MIG)-[0-9A-Za-z/-]{1,80})){0,15}",
    "CUDA_MPS_ACTIVE_THREAD_PERCENTAGE": r"(100|[1-9]?\d)(\.\d{1,6})?",
    "CUDA_MPS_PINNED_DEVICE_MEM_LIMIT": r"\d{1,3}=\d{1,9}[MG](,\d{1,3}=\d{1,9}[MG]){0,15}",
}


@dataclass
class GpuShare:
    """Start one stage's processes again with a new GPU share (allocator -> the launcher of its host). MPS
    fixes a process's share when it makes its CUDA context: the launcher stops the stage's processes at their
    safe point (``Stop``, reason ``STOP_TO_RESTART``) and starts them with ``env`` (counted in
    ``launcher/requotas``); only in a run with the allocator. ``env`` holds only the variables a share is made
    of (:data:`GPU_SHARE_VARIABLES`), each in its own format: anything else (a library for CUDA to load) is
    refused."""

    KEY = "ebrl/ctl/<run>/launcher/<host>/gpu_share"
    version: int = doc("plan version; a share whose version the stage already has is ignored")
    stage: Literal["gen", "train"] = doc("the stage whose processes take the share")
    env: dict[str, str] = doc("the CUDA variables its processes start with: CUDA_VISIBLE_DEVICES, CUDA_MPS_*")

    MAX_BYTES = CONTROL_MAX_BYTES

    def check(self) -> None:
        _count("GpuShare.version", self.version)

    def __post_init__(self) -> None:
        other = sorted(k for k in self.env if k not in GPU_SHARE_VARIABLES)
        if other:
            raise MessageError(f"GpuShare: env may only set {', '.join(GPU_SHARE_VARIABLES)}, not {', '.join(other)}")
        for name, value in self.env.items():
            if not re.fullmatch(GPU_SHARE_VARIABLES[name], value):
                raise MessageError(f"GpuShare: {name}={value!r} is not a share's value")


MESSAGES: tuple[type, ...] = (
    Observation,
    ActionChunk,
    TrajectorySegment,
    SegmentBatch,
    ReplayRequest,
    ReplaySample,
    Weights,
    WeightsPart,
    StatsReport,
    SpanBatch,
    Event,
    EpisodeBatch,
    Stop,
    Affinity,
    Quota,
    GpuShare,
)

# --- validation ----------------------------------------------------------------------


def to_wire(msg: Any) -> dict[str, Any]:
    """The msgpack-able map of a message (shallow: arrays stay arrays)."""
    out = {f.name: getattr(msg, f.name) for f in dataclasses.fields(msg)}
    out["v"] = SCHEMA_VERSION
    return out


def encode_message(msg: Any) -> bytes:
    return codec.encode(to_wire(msg))


def decode_message(cls: type[T], payload: bytes | memoryview) -> T:
    """Decode and validate ``payload`` as ``cls``; raise :class:`MessageError` if it is not one (an
    :class:`OversizedError` before decoding anything when it is over ``cls.MAX_BYTES``)."""
    limit = getattr(cls, "MAX_BYTES", None)
    if limit is not None and len(payload) > limit:
        raise OversizedError(f"{cls.__name__}: {len(payload)} bytes, over its limit of {limit}")
    try:
        raw = codec.decode(payload)
    except codec.DecodeError as exc:
        raise MessageError(f"undecodable payload: {exc}") from None
    return from_wire(cls, raw)


def accept(cls: type[T], msg: Any) -> T:
    """The in-process counterpart of :func:`decode_message`, for a message handed over by reference between
    services of one process (``ebrl.bus.local``): ``msg`` must be a ``cls``; it is checked exactly as a decoded
    one (types, shapes, meaning) and comes back as a new ``cls`` whose arrays are read-only views of the
    sender's: nothing is copied, and neither side can change what the other holds through it."""
    if type(msg) is not cls:
        raise MessageError(f"{cls.__name__}: got a {type(msg).__name__} in the process")
    raw = {f.name: _read_only(getattr(msg, f.name)) for f in dataclasses.fields(cls)}
    raw["v"] = SCHEMA_VERSION
    return from_wire(cls, raw)


def _read_only(value: Any) -> Any:
    if isinstance(value, np.ndarray):
        value = value.view()
        value.flags.writeable = False
    return value


def array_bytes(msg: Any) -> int:
    """The bytes of a message's arrays: what its payload would be, less the small header (a bound on a message
    passed by reference is checked on it before it is accepted)."""
    return sum(v.nbytes for v in vars(msg).values() if isinstance(v, np.ndarray))


def from_wire(cls: type[T], raw: Any) -> T:
    if not isinstance(raw, dict):
        raise MessageError(f"{cls.__name__}: expected a map, got {type(raw).__name__}")
    version = raw.get("v")
    if type(version) is not int or version != SCHEMA_VERSION:  # an array's != is elementwise; True == 1
        shown = version if type(version) is int else typecheck.describe(version)
        raise MessageError(f"{cls.__name__}: schema version {shown}, expected {SCHEMA_VERSION}")
    hints = _hints(cls)
    values = {}
    for f in dataclasses.fields(cls):
        if f.name in raw:
            values[f.name] = typecheck.check(raw[f.name], hints[f.name], f"{cls.__name__}.{f.name}", MessageError)
        elif f.default is dataclasses.MISSING:
            raise MessageError(f"{cls.__name__}: missing field {f.name!r}")
    unknown = set(raw) - set(hints) - {"v"}
    if unknown:
        raise MessageError(f"{cls.__name__}: unknown fields {sorted(unknown, key=repr)}")  # str and bytes keys
    msg = cls(**values)
    check = getattr(msg, "check", None)
    if check is not None:
        try:
            check()
        except MessageError:
            raise
        except Exception as exc:  # a check that trips over a value it did not expect: still a bad message
            raise MessageError(f"{cls.__name__}: {type(exc).__name__}: {exc}") from None
    return msg


_HINTS: dict[type, dict[str, Any]] = {}


def _hints(cls: type) -> dict[str, Any]:
    if cls not in _HINTS:
        _HINTS[cls] = typing.get_type_hints(cls, include_extras=True)
    return _HINTS[cls]


STATS_FAMILIES: dict[str, type] = {"spans": SpanBatch, "events": Event, "episodes": EpisodeBatch}


def decode_stats_sample(key: str, payload: bytes | memoryview) -> "StatsReport | SpanBatch | Event | EpisodeBatch":
    """Decode a sample from ``ebrl/stats/<run>/**``: a ``SpanBatch`` on ``spans/<lane>``, an ``Event``
    on ``events/<service>``, an ``EpisodeBatch`` on ``episodes/<service>``, else a ``StatsReport``; raise
    :class:`MessageError` if it is none. Its ``local`` accepts one handed over in the process
    (``ebrl.bus.local``)."""
    return decode_message(_stats_class(key), payload)  # type: ignore[return-value]


def _stats_class(key: str) -> type:
    try:
        family = keys.parse(key).family
    except ValueError:
        family = "report"
    return STATS_FAMILIES.get(family, StatsReport)


decode_stats_sample.local = lambda key, msg: accept(_stats_class(key), msg)  # type: ignore[attr-defined]


# --- JSON Schema ------------------------------------------------------------------------


def json_schema(cls: type) -> dict[str, Any]:
    """JSON Schema (draft 2020-12) of one message type, as it appears after msgpack decoding."""
    hints = _hints(cls)
    props: dict[str, Any] = {"v": {"const": SCHEMA_VERSION, "description": "schema version"}}
    required = ["v"]
    for f in dataclasses.fields(cls):
        prop = _schema_of(hints[f.name])
        prop["description"] = f.metadata.get("doc", "")
        props[f.name] = prop
        if f.default is dataclasses.MISSING:
            required.append(f.name)
    return {
        "$schema": "https://json-schema.org/draft/2020-12/schema",
        "$id": f"ebrl/{cls.__name__}.json",
        "title": cls.__name__,
        "description": (cls.__doc__ or "").strip(),
        "x-ebrl-key": cls.KEY,
        "x-ebrl-max-bytes": cls.MAX_BYTES,
        "type": "object",
        "properties": props,
        "required": required,
        "additionalProperties": False,
    }


def _schema_of(tp: Any) -> dict[str, Any]:
    origin = get_origin(tp)
    if origin is Annotated:
        base, *extra = get_args(tp)
        spec = next((e for e in extra if isinstance(e, Array)), None)
        if spec is not None:
            return {
                "x-ebrl-ndarray": {"dtype": spec.dtype or "numeric", "ndim": spec.ndim},
                "description": "numpy array (msgpack extension type 1, see ebrl/codec.py)",
            }
        return _schema_of(base)
    if origin in (types.UnionType, typing.Union):
        return {"anyOf": [_schema_of(a) for a in get_args(tp)]}
    if origin is Literal:
        return {"enum": list(get_args(tp))}
    if origin is list:
        return {"type": "array", "items": _schema_of(get_args(tp)[0])}
    if origin is dict:
        return {"type": "object", "additionalProperties": _schema_of(get_args(tp)[1])}
    names = {float: "number", int: "integer", bool: "boolean", str: "string", type(None): "null"}
    return {"type": names[tp]}


def write_schemas(directory: str) -> list[str]:
    """Write one ``<Message>.json`` per message type into ``directory``; return the paths."""
    import os

    os.makedirs(directory, exist_ok=True)
    paths = []
    for cls in MESSAGES:
        path = os.path.join(directory, f"{cls.__name__}.json")
        with open(path, "w") as fh:
            fh.write(json.dumps(json_schema(cls), indent=2) + "\n")
        paths.append(path)
    return paths
