"""The replay's messages: transitions in and minibatch requests (train -> replay), minibatches out
(replay -> train)."""

from __future__ import annotations

from dataclasses import dataclass
from typing import Annotated, Any

import numpy as np

from ebrl.messages.common import DATA_MAX_BYTES, MAX_VERSION, MessageError, all_finite, doc, in_range
from ebrl.typecheck import Array

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
    all_finite(name, msg.obs, msg.actions, msg.rewards, msg.next_obs)
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
        in_range("ReplayRequest.seq", self.seq)
        in_range("ReplayRequest.session", self.session, 0, (1 << 63) - 1)
        in_range("ReplayRequest.acked", self.acked, 0, (1 << 62))
        in_range("ReplayRequest.batches", self.batches, 0, 1 << 16)
        in_range("ReplayRequest.batch_size", self.batch_size, 1, 1 << 24)
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
        in_range("ReplaySample.seq", self.seq)
        in_range("ReplaySample.session", self.session, 0, (1 << 63) - 1)
        in_range("ReplaySample.size", self.size, 0, 1 << 40)
        in_range("ReplaySample.inserted", self.inserted, 0, 1 << 62)
        _transitions("ReplaySample", self)
