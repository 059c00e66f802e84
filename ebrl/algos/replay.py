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

import io
import math
from dataclasses import dataclass
from pathlib import Path

import numpy as np

from ebrl.algos.checkpoint import write_durably
from ebrl.messages import TrajectorySegment

FIELDS = ("obs", "actions", "rewards", "steps", "terminal", "next_obs", "versions")


def transition_bytes(obs_size: int, action_size: int) -> int:
    """Host bytes of one transition: two float32 observations, a float32 chunk, the reward (float32), steps
    (int32), the terminal flag (bool) and the acting version (int64)."""
    return 4 * (2 * obs_size + action_size) + 4 + 4 + 1 + 8


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
        """The segment's decisions as transitions (checked against the buffer's sizes first: a segment that does
        not match raises ValueError and adds nothing); returns how many were added."""
        t = len(seg.obs)
        obs = seg.obs.reshape(t, -1)
        actions = seg.actions.reshape(t, -1)
        if obs.shape[1] != self.obs_size or actions.shape[1] != self.action_size or seg.images.shape[-1]:
            raise ValueError(f"a segment of {obs.shape[1]} observation and {actions.shape[1]} action values per "
                             f"decision{' with image bytes' if seg.images.shape[-1] else ''}; this replay holds "
                             f"{self.obs_size} and {self.action_size}")
        if t == 0:
            return 0
        next_obs = np.concatenate([obs[1:], seg.last_obs.reshape(1, -1)])
        terminal = np.zeros(t, bool)
        terminal[-1] = seg.end == "terminated"
        rows = (self.cursor + np.arange(t)) % self.capacity
        if t > self.capacity:  # more than fits: the newest capacity of them
            rows, keep = rows[-self.capacity:], slice(t - self.capacity, t)
        else:
            keep = slice(0, t)
        self.obs[rows], self.next_obs[rows], self.actions[rows] = obs[keep], next_obs[keep], actions[keep]
        self.rewards[rows], self.steps[rows], self.terminal[rows] = seg.rewards[keep], seg.steps[keep], terminal[keep]
        self.versions[rows] = seg.versions[keep]
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

    def save(self, path: str | Path) -> None:
        """The contents, durably (written to a temporary, fsynced, renamed): what ``restore`` reads."""
        meta = np.array([self.obs_size, self.action_size, self.capacity, self.size, self.cursor, self.inserted],
                        np.int64)

        def write(f: io.BufferedWriter) -> None:
            np.savez(f, meta=meta, **{name: getattr(self, name)[:self.size] for name in FIELDS})

        write_durably(Path(path), write)

    def restore(self, path: str | Path) -> int:
        """Read back what ``save`` wrote; the transitions restored. ValueError where the file does not fit this
        buffer's sizes or its values are not finite (then the buffer stays as it was)."""
        with np.load(Path(path), allow_pickle=False) as data:
            obs_size, action_size, _, size, cursor, inserted = (int(x) for x in data["meta"])
            arrays = {name: data[name] for name in FIELDS}
        if (obs_size, action_size) != (self.obs_size, self.action_size) or size > self.capacity:
            raise ValueError(f"{path}: {size} transitions of {obs_size} + {action_size} values, for a replay of "
                             f"{self.capacity} of {self.obs_size} + {self.action_size}")
        if any(len(a) != size for a in arrays.values()) or not all(
                np.isfinite(arrays[name]).all() for name in ("obs", "next_obs", "actions", "rewards")):
            raise ValueError(f"{path}: arrays of the wrong length or values that are not finite")
        for name, values in arrays.items():
            getattr(self, name)[:size] = values
        self.size, self.cursor, self.inserted = size, cursor % self.capacity, inserted
        return size
