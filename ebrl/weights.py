"""Versioned weights over the bus: one message while small, parts when large, assembled off the event loop.

A version under ``SINGLE_MAX_BYTES`` goes as one :class:`~ebrl.messages.Weights` on ``keys.weights``; a
larger one as :class:`~ebrl.messages.WeightsPart` messages of ``PART_BYTES`` on ``keys.weights_parts``.
Parts fit Zenoh's shared-memory pool (16 MiB by default; on one host every put of 3 KiB or more goes
through it) and no single part holds the GIL for long on either side: a 500 MB message would stall the
receiving event loop for as long as one copy of it takes.

Both sides use only the bus API (:class:`~ebrl.bus.session.BusBase`: Zenoh, or the in-memory bus in tests) and
keep its blocking calls off the event loop. The publisher has one thread that packs and
sends versions and answers late joiners' queries in order, so a query never sees the send buffer being
rewritten; a version still waiting while a newer one is published is skipped (keep-latest). Parts go
with blocking congestion control and are never dropped to make room. The receiver assembles parts on
the bus's callback thread into one buffer per version; a newer version discards an incomplete older one,
and only a complete version is ever handed out. The receiver assembles the next version into the last
one's buffer once nothing refers to that any more: first-touch page faults on a fresh buffer cost about
as much as the whole transfer (measured: filling 500 MB took 1.5 s fresh, 0.1 s reused).

Nothing that arrives is trusted (:class:`WeightsLayout`, :func:`plausible`): a receiver that knows its
policy takes only versions of exactly its tensors (names, dtypes, shapes; a part's ``total_bytes`` must be
the policy's size, so a crafted part never allocates more) with finite values, and only versions that are
plausible counters: a version may run ahead of the newest one it has by at most ``MAX_JUMP`` plus
``MAX_RATE`` per second since then, so a forged version far in the future cannot make it ignore the
real updates after it. A version that fails any check is dropped and counted (``bus/malformed``,
``weights_refused``) and changes nothing.
"""

from __future__ import annotations

import asyncio
import logging
import math
import os
import queue
import sys
import threading
import time
from dataclasses import dataclass, field
from typing import Callable, Literal

import numpy as np

from ebrl import graph
from ebrl.bus.session import BusBase, Query
from ebrl.messages import MessageError, StatsReport, Weights, WeightsPart, decode_message, encode_message

log = logging.getLogger("ebrl.weights")

SINGLE_MAX_BYTES = 4 << 20  # a version this large or larger goes in parts
MAX_JUMP = 64  # a version may be this far past the receiver's newest, plus MAX_RATE per second since it came
MAX_RATE = 200.0  # versions per second: no update of a real policy is this fast (the quickstart's: ~3 per second)
AHEAD_S = 2.0  # a receiver ahead of the trainer's reported version this long, in AHEAD_REPORTS reports in a row,
AHEAD_REPORTS = 3  # goes back to the trainer's weights (a report is at most one update behind a real receiver)
PART_BYTES = 4 << 20  # four fit the default 16 MiB shared-memory pool; a 256 MiB pool measured no better
ALIGN = 64  # each array starts at a multiple of this in a version's buffer


@dataclass
class PublishStats:
    """What one :meth:`WeightsPublisher.publish` did."""

    version: int
    sent: bool  # False: a newer version was published before this one's turn came
    mode: Literal["whole", "parts", ""] = ""
    total_bytes: int = 0
    parts: int = 0
    pack_s: float = 0.0  # encoding, or copying the arrays into the send buffer
    send_s: float = 0.0  # handing every message to the bus (blocking puts)


@dataclass
class _Pending:
    version: int
    arrays: dict[str, np.ndarray]
    created_at: float
    future: asyncio.Future


@dataclass
class _Latest:
    """The newest version sent, as the queryable serves it: the encoded message, or the parts' buffer."""

    version: int
    created_at: float
    whole: bytes | None = None
    names: list[str] = field(default_factory=list)
    dtypes: list[str] = field(default_factory=list)
    shapes: list[list[int]] = field(default_factory=list)
    offsets: list[int] = field(default_factory=list)
    count: int = 0


class WeightsPublisher:
    """Publish weight versions (train's side) and answer late joiners with the newest one."""

    def __init__(self, bus: BusBase, run: str, *, part_bytes: int = PART_BYTES,
                 single_max_bytes: int = SINGLE_MAX_BYTES):
        self.bus, self.run = bus, run
        self.keys = graph.keys_of(run, "train")
        self.part_bytes, self.single_max_bytes = part_bytes, single_max_bytes
        self.published = 0
        self.superseded = 0
        self._lock = threading.Lock()
        self._pending: _Pending | None = None
        self._latest: _Latest | None = None  # worker thread only
        self._buffer = np.zeros(0, np.uint8)  # worker thread only; reused while the size stays the same
        self._jobs: queue.SimpleQueue[Callable[[], None] | None] = queue.SimpleQueue()
        self._queryable = bus.declare_queryable_raw(self.keys.answer("weights"), self._on_query)
        self._thread = threading.Thread(target=self._work, name="ebrl-weights", daemon=True)
        self._thread.start()

    async def publish(self, version: int, arrays: dict[str, np.ndarray],
                      created_at: float | None = None) -> PublishStats:
        """Send ``arrays`` as ``version``; returns once the bus has every message, or once a newer version took
        this one's place. ``arrays`` must stay unchanged until then (pass a snapshot, e.g. ``state_arrays``)."""
        future = self.bus.loop.create_future()
        job = _Pending(version, arrays, time.time() if created_at is None else created_at, future)
        with self._lock:
            older, self._pending = self._pending, job
        if older is not None:
            self.superseded += 1
            _settle(older.future, PublishStats(older.version, sent=False))
        self._jobs.put(self._send_pending)
        return await future

    def close(self) -> None:
        self._jobs.put(None)
        try:
            self._queryable.undeclare()
        except Exception as exc:  # the session may be closed already
            log.debug("weights publisher close: %s", exc)

    # --- worker thread ------------------------------------------------------------------

    def _work(self) -> None:
        while (job := self._jobs.get()) is not None:
            try:
                job()
            except Exception as exc:  # a closed session at shutdown, mostly
                log.warning("weights publisher: %s", exc)

    def _send_pending(self) -> None:
        with self._lock:
            job, self._pending = self._pending, None
        if job is None:  # an earlier call already sent the newest
            return
        try:
            stats = self._send(job)
        except Exception as exc:  # the caller's await raises it
            self.bus.loop.call_soon_threadsafe(_settle, job.future, None, exc)
            return
        self.published += 1
        self.bus.loop.call_soon_threadsafe(_settle, job.future, stats)

    def _send(self, job: _Pending) -> PublishStats:
        start = time.perf_counter()
        names = list(job.arrays)
        arrays = [np.asarray(job.arrays[name], order="C") for name in names]
        offsets, total = [], 0
        for array in arrays:
            offsets.append(total)
            total += -(-array.nbytes // ALIGN) * ALIGN
        if total < self.single_max_bytes:
            payload = encode_message(Weights(version=job.version, params=dict(zip(names, arrays)),
                                             created_at=job.created_at))
            packed = time.perf_counter()
            self.bus.put_bytes_blocking(self.keys.put("weights"), payload)
            self._latest = _Latest(job.version, job.created_at, whole=payload)
            return PublishStats(job.version, True, "whole", len(payload), 1, packed - start,
                                time.perf_counter() - packed)
        if len(self._buffer) != total:
            self._buffer = np.zeros(total, np.uint8)  # zeros: the padding between arrays never leaks memory
        for array, offset in zip(arrays, offsets):
            flat = array.reshape(-1).view(np.uint8)
            np.copyto(self._buffer[offset:offset + len(flat)], flat)
        latest = _Latest(job.version, job.created_at, names=names, dtypes=[a.dtype.str for a in arrays],
                         shapes=[list(a.shape) for a in arrays], offsets=offsets,
                         count=-(-total // self.part_bytes))
        self._latest = latest
        packed = time.perf_counter()
        parts_key = self.keys.put("parts")
        for index in range(latest.count):
            self.bus.put_bytes_blocking(parts_key, self._part(latest, index))
        return PublishStats(job.version, True, "parts", total, latest.count, packed - start,
                            time.perf_counter() - packed)

    def _part(self, latest: _Latest, index: int) -> bytes:
        begin = index * self.part_bytes
        part = WeightsPart(version=latest.version, index=index, count=latest.count, part_bytes=self.part_bytes,
                           total_bytes=len(self._buffer), created_at=latest.created_at,
                           data=self._buffer[begin:begin + self.part_bytes])
        if index == 0:
            part.names, part.dtypes, part.shapes, part.offsets = (latest.names, latest.dtypes, latest.shapes,
                                                                  latest.offsets)
        return encode_message(part)

    def _on_query(self, query: Query) -> None:  # a bus thread: hand over, never reply here
        self._jobs.put(lambda: self._answer(query))

    def _answer(self, query: Query) -> None:
        """Reply with the newest version: the one message, or every part (a late joiner gets it whole)."""
        try:
            latest = self._latest
            if latest is None:
                return
            whole_key, parts_key = self.keys.put("weights"), self.keys.put("parts")
            if latest.whole is not None:
                if query.matches(whole_key):
                    query.reply(whole_key, latest.whole)
            elif query.matches(parts_key):
                for index in range(latest.count):
                    query.reply(parts_key, self._part(latest, index))
        finally:
            query.finish()


def _settle(future: asyncio.Future, result: PublishStats | None, error: BaseException | None = None) -> None:
    if future.done():  # the caller gave up waiting
        return
    if error is not None:
        future.set_exception(error)
    else:
        future.set_result(result)


@dataclass(frozen=True)
class WeightsLayout:
    """The tensors a receiver's policy has: name -> (numpy dtype string, shape). A version is taken only if it
    carries exactly these."""

    tensors: dict[str, tuple[str, tuple[int, ...]]]

    @classmethod
    def of(cls, arrays: dict[str, np.ndarray]) -> "WeightsLayout":
        return cls({name: (a.dtype.str, tuple(a.shape)) for name, a in arrays.items()})

    @classmethod
    def of_model(cls, model) -> "WeightsLayout":
        """From a torch module's state dict, without copying it."""
        return cls({name: (np.dtype(str(t.dtype).removeprefix("torch.")).str, tuple(t.shape))
                    for name, t in model.state_dict().items()})

    @property
    def total_bytes(self) -> int:
        """The buffer a version in parts takes (each array at an ``ALIGN``-byte boundary, as published)."""
        return sum(-(-math.prod(shape) * np.dtype(dtype).itemsize // ALIGN) * ALIGN
                   for dtype, shape in self.tensors.values())

    def check(self, version: int, params: dict[str, np.ndarray]) -> None:
        """MessageError unless ``params`` are exactly this layout's tensors, every value finite."""
        if set(params) != set(self.tensors):
            missing, extra = sorted(set(self.tensors) - set(params)), sorted(set(params) - set(self.tensors))
            raise MessageError(f"weights v{version}: tensors differ from the policy's (missing {missing[:5]}, "
                               f"unexpected {extra[:5]})")
        for name, array in params.items():
            dtype, shape = self.tensors[name]
            if array.dtype.str != dtype or tuple(array.shape) != shape:
                raise MessageError(f"weights v{version}: {name} is {array.dtype.str}{list(array.shape)}, the "
                                   f"policy's {dtype}{list(shape)}")
            if array.dtype.kind == "f" and not np.isfinite(array).all():
                raise MessageError(f"weights v{version}: {name} holds a value that is not finite")


def known_version(run_dir: str) -> int:
    """The newest policy version a process starting in ``run_dir`` knows exists: the one the launcher saw
    before a restart (``procenv.version_floor``) or the run's newest checkpoint directory (a resumed run;
    ``RUN_DIR/checkpoints/v<version>``, read without torch); -1: none."""
    from ebrl import procenv

    floor = procenv.version_floor()
    try:
        names = os.listdir(os.path.join(run_dir, "checkpoints"))  # ebrl.algos.checkpoint.DIRNAME
    except OSError:
        return floor
    return max([floor, *(int(name[1:]) for name in names if name[:1] == "v" and name[1:].isdigit())])


def plausible(version: int, newest: int, since_s: float) -> bool:
    """Whether ``version`` can follow ``newest`` (the newest version taken, or the floor a receiver started
    from) ``since_s`` seconds after it came: at most ``MAX_JUMP`` plus ``MAX_RATE`` per second ahead."""
    return version <= newest + MAX_JUMP + MAX_RATE * max(0.0, since_s)


@dataclass
class _Assembly:
    """One version being put together from its parts."""

    version: int
    count: int
    part_bytes: int
    total_bytes: int
    created_at: float
    buffer: np.ndarray
    have: set[int] = field(default_factory=set)
    params: dict[str, np.ndarray] | None = None  # views into buffer, from part 0's manifest


class WeightsReceiver:
    """The newest complete weights version (gen's side), assembled on the bus's thread.

    ``notify`` is set on the event loop whenever a newer version is complete; the event loop then only
    takes it (:meth:`take_newer`). Malformed messages are counted on the bus and dropped.

    ``layout`` (the receiver's policy) makes it take only versions of exactly those tensors, finite;
    ``floor`` is the newest version known to exist when it starts (a resumed run's checkpoint, the newest
    seen before a restart), from which the first version must be :func:`plausible`. ``follow``: read the
    trainer's reports all along (:meth:`follow_trainer`), so a receiver put ahead of it goes back. ``role``: the
    reader's role in the service graph (``gen`` or ``eval``), whose declared keys it uses."""

    def __init__(self, bus: BusBase, run: str, *, notify: asyncio.Event | None = None,
                 layout: WeightsLayout | None = None, floor: int = -1, follow: bool = False,
                 max_bytes: int | None = None, role: str = "gen"):
        self.bus, self.run, self._notify, self.layout = bus, run, notify, layout
        self.keys = graph.keys_of(run, role)  # gen's or eval's: the graph's weights readers
        self.max_bytes = max_bytes  # a weights message's bound in this run (ebrl.sizes); None: the bus's alone
        self.version = -1  # newest complete version so far
        self.completed = 0  # versions assembled or received whole
        self.discarded = 0  # incomplete versions given up for a newer one
        self.stale = 0  # messages of a version older than one already here
        self.refused = 0  # versions too far ahead to be real (plausible), or that failed the layout
        self.resets = 0  # times it found itself ahead of the trainer and went back to the trainer's (trainer_at)
        self._ahead = (0.0, 0)  # since when, and in how many reports in a row, the trainer is behind the receiver
        self._reset = False  # take_newer hands out the next version even though it is older than the taker's
        self._anchor = (floor, time.monotonic())  # (newest version taken or the floor, when): plausible() from it
        self._parts_key = graph.keys_of(run, "train").put("parts")  # what training sends parts on
        self._lock = threading.Lock()  # assembly state; held while a part is copied in
        self._handoff = threading.Lock()  # only _latest, so taking it never waits for a copy
        self._assembly: _Assembly | None = None
        self._latest: Weights | None = None
        self._spare: np.ndarray | None = None  # the previous version's buffer, reused once it is free
        bus.subscribe_raw(self.keys.sub("weights"), self._on_payload, max_bytes)
        # made in a running event loop (gen's and eval's setup); the loop holds tasks weakly, so keep a reference
        self.follower = asyncio.get_running_loop().create_task(self.follow_trainer()) if follow else None

    def counters(self) -> dict[str, int]:
        """What the taker reports (``gen/...``): versions discarded incomplete, refused, and resets."""
        return {"weights_discarded": self.discarded, "weights_refused": self.refused, "version_resets": self.resets}

    def reject(self, weights: Weights, current: int) -> None:
        """The taker could not load ``weights`` (it stays at version ``current``): the version never counted,
        so the next real version is taken again."""
        with self._lock:
            if self.version == weights.version:
                self.version = current
                self._anchor = (current, time.monotonic())
            self.refused += 1

    def take_newer(self, version: int) -> Weights | None:
        """The newest complete version if it is newer than ``version`` (or, after the receiver found itself
        ahead of every trainer, the trainer's newest even though it is older); the receiver forgets it then, so
        its memory goes once the caller is done with it."""
        with self._handoff:
            if self._latest is None or (self._latest.version <= version and not self._reset):
                return None
            latest, self._latest, self._reset = self._latest, None, False
            return latest

    async def request(self, timeout: float = 10.0) -> bool:
        """Ask the publisher for its newest version (how a late joiner gets its first weights without waiting
        for the next update); True if a version newer than any taken is complete now."""
        # Every reply (parts share one key, so none may be merged), each assembled as it arrives.
        await self.bus.get_raw(self.keys.query("weights"), self._on_payload, timeout=timeout)
        return self._latest is not None

    def _on_payload(self, key: str, payload: bytes) -> None:  # a bus thread, or the query's
        if not self.bus.fits(key, len(payload), self.max_bytes):  # for replies to request(); samples: checked already
            return
        try:
            if key == self._parts_key:
                self._on_part(decode_message(WeightsPart, payload))
            else:
                self._on_whole(decode_message(Weights, payload))
        except Exception as exc:  # MessageError, or a part that contradicts its version (MemoryError...)
            self.bus.count_malformed(key, exc)

    def _admit(self, version: int) -> None:  # under self._lock
        newest, since = self._anchor
        if not plausible(version, newest, time.monotonic() - since):
            self.refused += 1
            raise MessageError(f"weights v{version}: implausibly far past v{newest} (at most {MAX_JUMP} + "
                               f"{MAX_RATE:g}/s ahead)")

    def trainer_at(self, version: int) -> bool:
        """The trainer reports ``version`` as its newest. A receiver ahead of it in ``AHEAD_REPORTS`` reports in a
        row, over ``AHEAD_S`` seconds or more, holds a version no trainer made (a forged one, plausibly
        numbered): it forgets it, counted in ``resets``, and takes whatever the trainer sends next, even an older
        number (True: ask the trainer now, :meth:`request`). Only the trainer's weights are ever taken, so a
        forged report costs one request."""
        now = time.monotonic()
        with self._lock:
            if self.version <= version:
                self._ahead = (now, 0)
                return False
            since, reports = self._ahead if self._ahead[1] else (now, 0)
            self._ahead = (since, reports + 1)
            if reports + 1 < AHEAD_REPORTS or now - since < AHEAD_S:
                return False
            log.warning("weights: v%d is ahead of the trainer's v%d for %.0f s: going back to the trainer's",
                        self.version, version, now - since)
            self.version, self._anchor, self._ahead, self._assembly = -1, (version, now), (0.0, 0), None
            self.resets += 1
            with self._handoff:
                self._latest, self._reset = None, True
        return True

    async def follow_trainer(self) -> None:
        """Read the trainer's reports (train/0's ``train/policy_version``) for as long as it runs; whenever the
        receiver is found ahead (:meth:`trainer_at`), ask for the trainer's newest weights."""
        reports = self.bus.subscribe(self.keys.sub("stats"), StatsReport, policy="latest", capacity=1)
        async for _, report in reports:
            version = report.metrics.get("train/policy_version")
            if version is not None and math.isfinite(version) and self.trainer_at(int(version)):
                await self.request()

    def _on_whole(self, weights: Weights) -> None:
        with self._lock:
            if weights.version <= self.version:
                self.stale += 1
                return
            self._admit(weights.version)
            if self.layout is not None:
                self.layout.check(weights.version, weights.params)
            self._complete(weights)

    def _on_part(self, part: WeightsPart) -> None:
        begin = part.index * part.part_bytes
        if not (part.total_bytes > 0 and part.part_bytes > 0 and part.count == -(-part.total_bytes // part.part_bytes)
                and 0 <= part.index < part.count and len(part.data) == min(part.part_bytes, part.total_bytes - begin)):
            raise MessageError(f"WeightsPart v{part.version}: part {part.index} of {part.count} does not fit "
                               f"{part.total_bytes} bytes in parts of {part.part_bytes}")
        # A version is told apart by its creation time too: a restarted train may send again a version number
        # its predecessor died sending, and parts of the two must never mix.
        ident = (part.version, part.created_at)
        if self.layout is not None and part.total_bytes != self.layout.total_bytes:  # before any buffer exists
            raise MessageError(f"WeightsPart v{part.version}: {part.total_bytes} bytes, the policy's weights are "
                               f"{self.layout.total_bytes}")
        with self._lock:
            building = self._assembly
            newest = None if building is None else (building.version, building.created_at)
            if part.version <= self.version or (newest is not None and ident < newest):
                self.stale += 1
                return
            self._admit(part.version)
            if newest is None or ident > newest:
                if building is not None:
                    self.discarded += 1
                    self._spare, self._assembly, building = building.buffer, None, None
                self._assembly = building = _Assembly(part.version, part.count, part.part_bytes, part.total_bytes,
                                                      part.created_at, self._buffer(part.total_bytes))
            elif (part.count, part.part_bytes, part.total_bytes) != (building.count, building.part_bytes,
                                                                     building.total_bytes):
                raise MessageError(f"WeightsPart v{part.version}: part {part.index} disagrees with earlier parts "
                                   f"on the version's size")
            if part.index == 0:
                building.params = _manifest_views(part, building.buffer)
            np.copyto(building.buffer[begin:begin + len(part.data)], part.data)
            building.have.add(part.index)
            if building.params is not None and len(building.have) == building.count:
                self._assembly, self._spare = None, building.buffer
                if self.layout is not None:  # a version that fails it is dropped whole (counted by the caller)
                    self.layout.check(building.version, building.params)
                self._complete(Weights(version=building.version, params=building.params,
                                       created_at=building.created_at))

    def _buffer(self, total: int) -> np.ndarray:  # under self._lock
        spare, self._spare = self._spare, None
        # Free when only `spare` and getrefcount's argument refer to it: every array view handed out holds a
        # reference to the buffer it views, so a version someone still reads is never overwritten.
        if spare is not None and len(spare) == total and sys.getrefcount(spare) == 2:
            return spare
        return np.empty(total, np.uint8)

    def _complete(self, weights: Weights) -> None:  # under self._lock
        if self._assembly is not None and self._assembly.version <= weights.version:
            self._assembly = None
            self.discarded += 1
        with self._handoff:
            self._latest = weights
        self.version = weights.version
        self._anchor = (weights.version, time.monotonic())
        self.completed += 1
        if self._notify is not None:
            try:
                self.bus.loop.call_soon_threadsafe(self._notify.set)
            except RuntimeError:  # loop closed during shutdown
                pass


def _manifest_views(part: WeightsPart, buffer: np.ndarray) -> dict[str, np.ndarray]:
    """Part 0's manifest as array views into ``buffer``; MessageError if any array falls outside it."""
    n = len(part.names)
    if not n == len(part.dtypes) == len(part.shapes) == len(part.offsets) or len(set(part.names)) != n:
        raise MessageError(f"WeightsPart v{part.version}: manifest lists differ in length or repeat a name")
    views = {}
    for name, dtype_str, shape, offset in zip(part.names, part.dtypes, part.shapes, part.offsets):
        try:
            dtype = np.dtype(dtype_str)
        except (TypeError, ValueError):
            raise MessageError(f"WeightsPart v{part.version}: {name} has an unknown dtype {dtype_str!r}") from None
        if dtype.hasobject or any(d < 0 for d in shape):
            raise MessageError(f"WeightsPart v{part.version}: {name} has dtype {dtype_str!r}, shape {shape}")
        nbytes = math.prod(shape) * dtype.itemsize
        if offset < 0 or offset + nbytes > len(buffer):
            raise MessageError(f"WeightsPart v{part.version}: {name} lies outside the version's {len(buffer)} bytes")
        views[name] = buffer[offset:offset + nbytes].view(dtype).reshape(shape)
    return views
