"""Training's side of the replay service: requests sent from the update thread, answers awaited there.

An off-policy algorithm's update (``ebrl.algos.offpolicy``) runs on train's update thread, the bus on its event
loop. :class:`ReplayLink` bridges the two: :meth:`ReplayLink.send` publishes a
:class:`~ebrl.messages.ReplayRequest` from the update thread (``ebrl/data/<run>/replay/request``) and returns at
once, so an update can ask for its next minibatches before it steps on the ones it has; :meth:`ReplayLink.wait`
blocks until the :class:`~ebrl.messages.ReplaySample` that answers it arrived (``.../replay/sample``, taken off
the bus by :meth:`ReplayLink.receive`, a task of the train service).

Where the replay shares train's process (``run.processes``), both messages are handed over by reference; else
they cross the bus. A request without an answer after ``RESEND_S`` is sent again as it was: a replay that died
and restarted answers it (its transitions are not added twice where they arrived before), and meanwhile training
waits, counted in ``train/replay_wait_s``. An answer is checked against its request (sizes, rows) before an
update uses it; one that does not fit is counted (``train/replay_refused``) and asked for again.
"""

from __future__ import annotations

import concurrent.futures
import logging
import secrets
import threading
import time
from typing import Any, Callable

import numpy as np

from ebrl.algos.replay import FIELDS, ReplayBatch
from ebrl import graph
from ebrl.messages import ReplayRequest, ReplaySample

log = logging.getLogger(__name__)

RESEND_S = 5.0  # a request without an answer this long is sent again (a replay restarting, a dropped message)


def make_request(session: int, seq: int, acked: int, rows: dict[str, np.ndarray] | None, batches: int,
                 batch_size: int, obs_size: int, action_size: int) -> ReplayRequest:
    """The request for ``rows`` (new transitions, :data:`~ebrl.algos.replay.FIELDS`; None: none) and then
    ``batches`` minibatches of ``batch_size``."""
    if rows is None:
        rows = {"obs": np.zeros((0, obs_size), np.float32), "actions": np.zeros((0, action_size), np.float32),
                "rewards": np.zeros(0, np.float32), "steps": np.zeros(0, np.int32), "terminal": np.zeros(0, bool),
                "next_obs": np.zeros((0, obs_size), np.float32), "versions": np.zeros(0, np.int64)}
    return ReplayRequest(session=session, seq=seq, acked=acked, batches=batches, batch_size=batch_size,
                         **{**rows, "terminal": rows["terminal"].view(np.uint8)})


def minibatches(sample: ReplaySample) -> ReplayBatch:
    """A sample's transitions as one :class:`~ebrl.algos.replay.ReplayBatch` (copied: writable arrays, which torch
    takes as they are)."""
    out = {name: np.array(getattr(sample, name)) for name in FIELDS}
    out["terminal"] = out["terminal"].view(bool)
    return ReplayBatch(**out)


class ReplayClosed(RuntimeError):
    """Training stops while an update waits for the replay."""


class ReplayLink:
    """Requests to one replay service and the answers that come back, matched by ``(session, seq)``."""

    def __init__(self, bus: Any, run: str, obs_size: int, action_size: int, count: Callable[[str, float], None],
                 max_bytes: int | None = None):
        self.bus, self.count = bus, count
        self.obs_size, self.action_size = obs_size, action_size
        train = graph.keys_of(run, "train")  # training asks the replay service
        self.request_key, self.sample_key = train.put("request"), train.sub("sample")
        self.samples = bus.subscribe(self.sample_key, ReplaySample, capacity=8, max_bytes=max_bytes)
        self.session = secrets.randbits(62)  # this process's: the replay tells a request sent again by it
        self.seq = 0
        self.acked = 0  # the replay's ``inserted`` by its last answer (ReplayRequest.acked)
        self.waiting: dict[int, concurrent.futures.Future] = {}
        self.lock = threading.Lock()
        self.closed = threading.Event()

    def send(self, rows: dict[str, np.ndarray] | None, batches: int, batch_size: int) -> tuple[ReplayRequest,
                                                                                                concurrent.futures.Future]:
        """Publish a request (any thread): ``rows``, new transitions (:data:`~ebrl.algos.replay.FIELDS`), or
        None; then ``batches`` minibatches of ``batch_size``. Returns it and the future of its answer."""
        with self.lock:
            self.seq += 1
            request = make_request(self.session, self.seq, self.acked, rows, batches, batch_size, self.obs_size,
                                   self.action_size)
            answer: concurrent.futures.Future = concurrent.futures.Future()
            self.waiting[request.seq] = answer
        self.bus.put_nowait(self.request_key, request)
        return request, answer

    def wait(self, request: ReplayRequest, answer: concurrent.futures.Future) -> ReplayBatch:
        """The minibatches that answer ``request`` (blocking; sent again every ``RESEND_S`` without an answer),
        as one :class:`~ebrl.algos.replay.ReplayBatch` of ``batches * batch_size`` rows, or of none where the
        replay held nothing. ReplayClosed when training stops meanwhile."""
        started = sent = time.monotonic()
        while True:
            if self.closed.is_set():
                raise ReplayClosed("training stopped while an update waited for the replay")
            try:
                sample = answer.result(timeout=0.2)
            except concurrent.futures.TimeoutError:
                if time.monotonic() - sent >= RESEND_S:
                    self.bus.put_nowait(self.request_key, request)  # the same session and seq: added once
                    self.count("train/replay_resent", 1)
                    sent = time.monotonic()
                continue
            if (why := self.refused(request, sample)) is None:
                break
            self.count("train/replay_refused", 1)  # asked again, as it was
            log.warning("replay: an answer refused (%s); asked again", why)
            with self.lock:
                answer = self.waiting[request.seq] = concurrent.futures.Future()
            self.bus.put_nowait(self.request_key, request)
            sent = time.monotonic()
        self.count("train/replay_wait_s", time.monotonic() - started)
        self.acked = sample.inserted
        return minibatches(sample)

    def refused(self, request: ReplayRequest, sample: ReplaySample) -> str | None:
        """Why an answer does not answer ``request`` (None: it does)."""
        rows = len(sample.rewards)
        if rows not in (0, request.batches * request.batch_size) or (rows == 0 and sample.size > 0
                                                                      and request.batches > 0):
            return f"{rows} transitions for {request.batches} x {request.batch_size}"
        if sample.obs.shape[1:] != (self.obs_size,) or sample.actions.shape[1:] != (self.action_size,):
            return f"transitions of {sample.obs.shape[1:]} + {sample.actions.shape[1:]} values"
        return None

    async def receive(self) -> None:
        """Answers off the bus to the requests waiting for them (a task of the train service); an answer to no
        waiting request of this process (sent again and answered twice, or to a train before it) is dropped."""
        async for _, sample in self.samples:
            if sample.session != self.session:
                continue
            with self.lock:
                answer = self.waiting.pop(sample.seq, None)
            if answer is not None:
                answer.set_result(sample)

    def close(self) -> None:
        """An update waiting for an answer ends (ReplayClosed)."""
        self.closed.set()


def connect_replay(bus: Any, cfg: Any, info: Any, algo: Any, count: Callable[[str, float], None],
                   max_bytes: int | None) -> ReplayLink | None:
    """The link to the run's replay service, connected to ``algo`` where it learns from one (else None)."""
    if not algo.uses_replay:
        return None
    link = ReplayLink(bus, cfg.run.name, info.layout.size, cfg.policy.chunk * info.action_dim, count, max_bytes)
    algo.connect(link)
    return link
