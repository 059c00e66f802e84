"""A replay buffer of chunk decisions for off-policy algorithms (SAC): transitions in a ring of fixed capacity.

A transition is one decision of a :class:`~ebrl.messages.TrajectorySegment`: the observation before the chunk,
the chunk as the env got it (flat, K x A), the chunk's reward (the sum of its steps' rewards), how many env steps
it ran and whether the episode terminated after it, and the observation after it (the next decision's, or the
segment's ``last_obs`` after its last decision). The target's discount, ``gamma ** steps`` and zero after a
terminal state, is the algorithm's: the buffer keeps the facts.

Sizes are fixed up front: ``capacity`` transitions and the bytes they take (:func:`transition_bytes`), refused
where they exceed the bound the caller gives (the replay service passes ``replay.max_bytes`` and what the host
has free). The oldest transitions are overwritten first. ``save`` writes the contents durably, ``restore`` reads
them back (a restarted replay resumes with what it held, or counts it lost where the file is missing or bad).
"""

from __future__ import annotations

import math
from dataclasses import dataclass
from pathlib import Path

import numpy as np
import psutil

from ebrl import durable
from ebrl.messages import TRANSITION_FIELDS, ReplayRequest, ReplaySample, TrajectorySegment

REPLAY_FILE = "replay.npz"  # RUN_DIR: the replay service's contents as of its last save (replay.save)
HOST_MEMORY_SHARE = 0.8  # most of the host's available memory a replay may take (replay.max_bytes = 0)
FIELDS = TRANSITION_FIELDS  # a transition's arrays, as the replay messages carry them


def replay_bound(max_bytes: int) -> float:
    """The bytes a replay may take: ``replay.max_bytes``, and never more than :data:`HOST_MEMORY_SHARE` of what
    the host has available now."""
    host = HOST_MEMORY_SHARE * psutil.virtual_memory().available
    return min(host, max_bytes) if max_bytes > 0 else host


def transition_bytes(obs_size: int, action_size: int) -> int:
    """Host bytes of one transition: two float32 observations, a float32 chunk, the reward (float32), steps
    (int32), the terminal flag (bool) and the acting version (int64)."""
    return 4 * (2 * obs_size + action_size) + 4 + 4 + 1 + 8


def transitions(seg: TrajectorySegment) -> dict[str, np.ndarray]:
    """A segment's decisions as transitions, a row each (:data:`FIELDS`): the chunk flat, the next observation
    the next decision's (the segment's ``last_obs`` after its last), terminal only after the last decision of a
    segment that ended its episode in a terminal state."""
    t = len(seg.obs)
    obs = seg.obs.reshape(t, -1)
    terminal = np.zeros(t, bool)
    terminal[-1:] = seg.end == "terminated"
    return {"obs": obs, "actions": seg.actions.reshape(t, -1), "rewards": seg.rewards, "steps": seg.steps,
            "terminal": terminal, "next_obs": np.concatenate([obs[1:], seg.last_obs.reshape(1, -1)]),
            "versions": seg.versions}


SAMPLE_BYTES = 4 << 20  # one ReplaySample carries about this many bytes of minibatches at most (one at least)


def batches_per_sample(batch_size: int, obs_size: int, action_size: int) -> int:
    """Minibatches of ``batch_size`` one :class:`~ebrl.messages.ReplaySample` carries: about ``SAMPLE_BYTES``."""
    return max(1, SAMPLE_BYTES // (batch_size * transition_bytes(obs_size, action_size)))


class ReplayTooLarge(ValueError):
    """A buffer whose arrays would not fit the bound; the message has the numbers."""


@dataclass
class ReplayBatch:
    """A sample of transitions, numpy arrays with one row per transition."""

    obs: np.ndarray  # [B, D] float32
    actions: np.ndarray  # [B, K*A] float32, as the env got them
    rewards: np.ndarray  # [B] float32
    steps: np.ndarray  # [B] int32: env steps the chunk ran
    terminal: np.ndarray  # [B] bool: the episode terminated after it (no bootstrap)
    next_obs: np.ndarray  # [B, D] float32
    versions: np.ndarray  # [B] int64: the policy version that acted

    def __len__(self) -> int:
        return len(self.rewards)

    def part(self, index: int, size: int) -> "ReplayBatch":
        """Rows ``index * size`` up to ``(index + 1) * size`` (views): one minibatch of several drawn together."""
        rows = slice(index * size, (index + 1) * size)
        return ReplayBatch(**{name: getattr(self, name)[rows] for name in FIELDS})


class ReplayBuffer:
    """``capacity`` transitions of ``obs_size`` float observations and ``action_size`` action values."""

    def __init__(self, obs_size: int, action_size: int, capacity: int, max_bytes: float = math.inf):
        if capacity <= 0:
            raise ValueError(f"replay capacity {capacity}: must be positive")
        need = capacity * transition_bytes(obs_size, action_size)
        if need > max_bytes:
            raise ReplayTooLarge(f"a replay of {capacity:,} transitions of {obs_size} observation and {action_size} "
                                 f"action values takes {need / 2**20:,.1f} MiB, over the bound of "
                                 f"{max_bytes / 2**20:,.1f} MiB: lower replay.capacity or raise replay.max_bytes")
        self.obs_size, self.action_size, self.capacity = obs_size, action_size, capacity
        self.nbytes = need
        self.obs = np.zeros((capacity, obs_size), np.float32)
        self.next_obs = np.zeros((capacity, obs_size), np.float32)
        self.actions = np.zeros((capacity, action_size), np.float32)
        self.rewards = np.zeros(capacity, np.float32)
        self.steps = np.zeros(capacity, np.int32)
        self.terminal = np.zeros(capacity, bool)
        self.versions = np.zeros(capacity, np.int64)
        self.size = 0  # transitions held
        self.cursor = 0  # where the next one goes
        self.inserted = 0  # transitions ever added (also those since overwritten)

    def add(self, seg: TrajectorySegment) -> int:
        """The segment's decisions as transitions (:func:`transitions`); returns how many were added."""
        if seg.images.shape[-1]:
            raise ValueError("a segment with image bytes: this replay holds float observations only")
        return self.add_rows(transitions(seg))

    def add_rows(self, rows: dict[str, np.ndarray]) -> int:
        """Transitions, one row per field of :data:`FIELDS` (checked against the buffer's sizes first: rows that
        do not match raise ValueError and add nothing); returns how many were added."""
        obs, actions, t = rows["obs"], rows["actions"], len(rows["rewards"])
        if obs.shape[1:] != (self.obs_size,) or actions.shape[1:] != (self.action_size,):
            raise ValueError(f"transitions of {obs.shape[1:]} observation and {actions.shape[1:]} action values; "
                             f"this replay holds {self.obs_size} and {self.action_size}")
        if any(len(rows[name]) != t for name in FIELDS):
            raise ValueError(f"transition fields of different lengths: {[len(rows[n]) for n in FIELDS]}")
        if t == 0:
            return 0
        positions = (self.cursor + np.arange(t)) % self.capacity
        if t > self.capacity:  # more than fits: the newest capacity of them
            positions, keep = positions[-self.capacity:], slice(t - self.capacity, t)
        else:
            keep = slice(0, t)
        for name in FIELDS:
            getattr(self, name)[positions] = rows[name][keep]
        self.cursor = (self.cursor + t) % self.capacity
        self.size = min(self.capacity, self.size + t)
        self.inserted += t
        return t

    def sample(self, n: int, rng: np.random.Generator) -> ReplayBatch:
        """``n`` transitions drawn uniformly with replacement (ValueError when the buffer is empty)."""
        if self.size == 0:
            raise ValueError("sampling an empty replay")
        idx = rng.integers(0, self.size, n)
        return ReplayBatch(**{name: getattr(self, name)[idx] for name in FIELDS})

    def save(self, path: str | Path, extra: dict[str, int] | None = None) -> None:
        """The contents and ``extra`` counters, durably (:func:`ebrl.durable.writing`): what ``restore``
        reads."""
        meta = np.array([self.obs_size, self.action_size, self.capacity, self.size, self.cursor, self.inserted],
                        np.int64)
        counters = {f"extra_{name}": np.array(value, np.int64) for name, value in (extra or {}).items()}
        with durable.writing(path) as tmp, open(tmp, "wb") as f:  # a file object: np.savez adds .npz to a name
            np.savez(f, meta=meta, **counters, **{name: getattr(self, name)[:self.size] for name in FIELDS})

    def restore(self, path: str | Path) -> tuple[int, dict[str, int]]:
        """Read back what ``save`` wrote: the transitions restored and the ``extra`` counters. ValueError where
        the file does not fit this buffer's sizes or its values are not finite (then the buffer stays as it
        was)."""
        with np.load(Path(path), allow_pickle=False) as data:
            obs_size, action_size, _, size, cursor, inserted = (int(x) for x in data["meta"])
            arrays = {name: data[name] for name in FIELDS}
            extra = {name[len("extra_"):]: int(data[name]) for name in data.files if name.startswith("extra_")}
        if (obs_size, action_size) != (self.obs_size, self.action_size) or not 0 <= size <= self.capacity:
            raise ValueError(f"{path}: {size} transitions of {obs_size} + {action_size} values, for a replay of "
                             f"{self.capacity} of {self.obs_size} + {self.action_size}")
        if any(len(a) != size for a in arrays.values()) or not all(
                np.isfinite(arrays[name]).all() for name in ("obs", "next_obs", "actions", "rewards")):
            raise ValueError(f"{path}: arrays of the wrong length or values that are not finite")
        for name, values in arrays.items():
            getattr(self, name)[:size] = values
        self.size, self.cursor, self.inserted = size, cursor % self.capacity, max(inserted, size)
        return size, extra


class ReplayStore:
    """The replay service's state (``ebrl/services/replay.py``): a :class:`ReplayBuffer` and what it answered.

    :meth:`exchange` takes one :class:`~ebrl.messages.ReplayRequest` (new transitions, then minibatches drawn
    uniformly) and returns its :class:`~ebrl.messages.ReplaySample`. A request sent again (the same session, a seq
    not above the newest added) adds nothing twice. A restarted store counts, on its first request, what
    training saw it take in (``acked``) beyond what it got back from its file as ``lost``."""

    def __init__(self, obs_size: int, action_size: int, capacity: int, max_bytes: float = math.inf, seed: int = 0,
                 max_rows: int = 1 << 20):
        self.buffer = ReplayBuffer(obs_size, action_size, capacity, max_bytes)
        self.max_rows = max_rows  # most transitions one answer draws (the run's ReplaySample bound)
        self.rng = np.random.default_rng(seed)
        self.sampled = self.lost = self.answered = 0
        self.newest = (-1, -1)  # (session, seq) of the newest request whose transitions are in

    def exchange(self, request: ReplayRequest) -> ReplaySample:
        """Add the request's transitions (unless added before), then draw its minibatches (none from an empty
        replay). ValueError, nothing added, where its sizes are not this replay's."""
        b, rows = self.buffer, {name: getattr(request, name) for name in FIELDS}
        if request.batches * request.batch_size > self.max_rows:
            raise ValueError(f"{request.batches} minibatches of {request.batch_size}: more than the {self.max_rows} "
                             "transitions an answer carries")
        rows["terminal"] = rows["terminal"].astype(bool)
        if self.answered == 0 and request.acked > b.inserted:  # restarted: what its file did not give back
            self.lost += request.acked - b.inserted
        session, seq = self.newest
        if request.session != session or request.seq > seq:
            b.add_rows(rows)  # ValueError where they do not fit
            self.newest = (request.session, request.seq)
        n = request.batches * request.batch_size if b.size else 0
        drawn = b.sample(n, self.rng) if n else None
        self.sampled += n
        self.answered += 1
        out = {name: getattr(drawn, name) if drawn is not None else getattr(b, name)[:0] for name in FIELDS}
        out["terminal"] = out["terminal"].view(np.uint8)
        return ReplaySample(session=request.session, seq=request.seq, size=b.size, inserted=b.inserted, **out)

    def save(self, path: str | Path) -> None:
        session, seq = self.newest
        self.buffer.save(path, {"sampled": self.sampled, "lost": self.lost, "session": session, "seq": seq})

    def restore(self, path: str | Path) -> int:
        """What :meth:`save` wrote (ValueError, OSError, KeyError where it cannot be read): transitions restored."""
        size, extra = self.buffer.restore(path)
        self.sampled, self.lost = extra.get("sampled", 0), extra.get("lost", 0)
        self.newest = (extra.get("session", -1), extra.get("seq", -1))
        return size
