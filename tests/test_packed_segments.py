"""A vectorized group's segments, packed: ``SegmentBuffers`` cuts exactly the segments per-env builders cut, a
``SegmentBatch`` survives the bus (images as bytes too) and refuses what does not add up, and training takes it
as the same segments (``ebrl/sched/rollout.py``, ``ebrl/messages/rollout.py``)."""

from __future__ import annotations

import asyncio
import dataclasses

import numpy as np
import pytest

from ebrl import obswire
from ebrl import keys
from ebrl.envs.obs import ObsField, ObsLayout
from ebrl.envs.worker import VectorChunk, WorkerFailed
from ebrl.messages import (ActionChunk, MessageError, SegmentBatch, TrajectorySegment, decode_message,
                           encode_message)
from ebrl.meter import Meter
from ebrl.sched.fleet import RolloutStats
from ebrl.sched.group import GroupLoop, SegmentOutbox, VectorGroupLoop
from ebrl.sched import rollout
from ebrl.sched.rollout import Episodes, SegmentBuffers, SegmentBuilder

N, K, A, D, LENGTH = 6, 3, 2, 5, 4
DECISION_BYTES = 4 * (D + K * A + 2 + 4) + 8  # float32 obs, actions, latents, 4 scalars; the int64 version
FRESH = np.full((N, D), 7.0, np.float32)  # a replaced group process's first observations
SEGMENT_FIELDS = ("obs", "actions", "latents", "logprobs", "values", "rewards", "steps", "versions", "last_obs")


def random_chunks(rng: np.random.Generator, chunks: int) -> list[tuple[np.ndarray, ActionChunk, VectorChunk, bool]]:
    """``chunks`` chunks of N envs as a batch answers them: episodes ending at random (terminated, truncated or
    both), some envs reporting success and some not, iteration boundaries every 5 chunks."""
    out, episode = [], np.zeros(N, np.int64)
    for c in range(chunks):
        obs = rng.standard_normal((N, D)).astype(np.float32)
        action = ActionChunk(group=1, seq=c, policy_version=c // 3, actions=rng.standard_normal((N, K, A)).astype(
            np.float32), logprobs=rng.standard_normal(N).astype(np.float32), values=rng.standard_normal(N).astype(
            np.float32), latents=rng.standard_normal((N, 2)).astype(np.float32))
        terminated, truncated = rng.random(N) < 0.15, rng.random(N) < 0.1
        ended = np.flatnonzero(terminated | truncated)
        steps = np.where(terminated | truncated, rng.integers(1, K + 1, N), K)
        result = VectorChunk(
            reward=rng.standard_normal(N).astype(np.float32), steps=steps, terminated=terminated, truncated=truncated,
            episode=episode.copy(), next_obs=rng.standard_normal((N, D)).astype(np.float32), ended=ended,
            final_obs=rng.standard_normal((len(ended), D)).astype(np.float32),
            episode_return=rng.standard_normal(len(ended)), episode_length=rng.integers(1, 50, len(ended)),
            episode_success=np.where(ended % 2 == 0, rng.integers(0, 2, len(ended)), -1).astype(np.int8),
            busy_s=0.01, step_s=(0.001,) * K)
        episode[ended] += 1
        out.append((obs, action, result, c % 5 == 4))
    return out


def same_segment(a: TrajectorySegment, b: TrajectorySegment) -> None:
    assert (a.group, a.env_id, a.episode, a.end, a.episode_offset) == (b.group, b.env_id, b.episode, b.end,
                                                                        b.episode_offset)
    for name in SEGMENT_FIELDS:
        x, y = getattr(a, name), getattr(b, name)
        assert x.dtype == y.dtype and np.array_equal(x, y), name
    assert a.episode_returns == pytest.approx(b.episode_returns, rel=1e-6)
    assert (a.episode_lengths, a.episode_successes) == (b.episode_lengths, b.episode_successes)


@pytest.mark.parametrize("packed_bytes", [rollout.PACKED_BYTES, 1000])  # 1000: a message of 1-3 segments
def test_packed_segments_are_the_per_env_builders_segments_through_the_bus(packed_bytes, monkeypatch):
    monkeypatch.setattr(rollout, "PACKED_BYTES", packed_bytes)
    rng = np.random.default_rng(7)
    messages = 0
    env_ids = np.arange(10, 10 + N)
    builders = [SegmentBuilder(1, int(e), LENGTH) for e in env_ids]
    buffers = SegmentBuffers(1, env_ids, LENGTH)
    expected, packed = [], []
    for obs, action, result, boundary in random_chunks(rng, 40):
        for i, res in enumerate(result.results()):
            seg = builders[i].add(obs[i], action.actions[i], action.latents[i], float(action.logprobs[i]),
                                  float(action.values[i]), action.policy_version, res, boundary)
            if seg is not None:
                expected.append(seg)
        for batch in buffers.add(obs, action, result, boundary):
            packed += decode_message(SegmentBatch, encode_message(batch)).segments()  # checked on the way
            messages += 1
            assert len(batch.env_ids) <= max(1, packed_bytes // (LENGTH * DECISION_BYTES))
        assert len(buffers) == sum(len(b) for b in builders)
    assert len(expected) == len(packed) > 40
    per_message = max(1, packed_bytes // (LENGTH * DECISION_BYTES))  # 3 at 1000 bytes
    assert (messages >= len(packed) / per_message) if per_message < N else (messages < len(packed))
    assert {s.end for s in packed} == {"cut", "terminated", "truncated"}
    assert any(s.episode_successes == [None] for s in packed) and any(s.episode_successes == [True] for s in packed)
    for a, b in zip(expected, packed):
        same_segment(a, b)
    at: dict[tuple[int, int], int] = {}  # (env, episode) -> env steps sent: each segment starts where the last ended
    for seg in packed:
        assert seg.episode_offset == at.get((seg.env_id, seg.episode), 0)
        at[(seg.env_id, seg.episode)] = seg.episode_offset + int(seg.steps.sum())
    assert any(seg.episode_offset > 0 for seg in packed)


def test_a_replaced_group_process_drops_the_segments_in_progress():
    rng = np.random.default_rng(1)
    buffers = SegmentBuffers(0, np.arange(N), LENGTH)
    obs, action, result, _ = random_chunks(rng, 1)[0]
    buffers.add(obs, action, result)
    in_progress = N - int((result.terminated | result.truncated).sum())
    assert len(buffers) == in_progress and buffers.drop() == in_progress and len(buffers) == 0


def packed(rng: np.random.Generator) -> SegmentBatch:
    buffers = SegmentBuffers(0, np.arange(N), LENGTH)
    for obs, action, result, _ in random_chunks(rng, 8):
        if batches := buffers.add(obs, action, result, boundary=True):
            return batches[0]
    raise AssertionError("no segments")


@pytest.mark.parametrize("change, why", [
    (lambda b: {"lengths": b.lengths + 1}, "sum\\(lengths\\)"),
    (lambda b: {"lengths": np.where(np.arange(len(b.lengths)) == 0, 0, b.lengths).astype(np.int32)}, "without"),
    (lambda b: {"episodes": b.episodes[1:]}, "per-segment fields differ"),
    (lambda b: {"last_obs": b.last_obs[:, :2]}, "last_obs has shape"),
    (lambda b: {"obs": np.where(b.obs == b.obs[0, 0], np.nan, b.obs).astype(np.float32)}, "not finite"),
    (lambda b: {"ends": np.full(len(b.ends), 3, np.int8)}, "ends: a value outside"),
    (lambda b: {"versions": b.versions - 10}, "versions: a value outside"),
    (lambda b: {"steps": b.steps + K + 1}, "steps: a value outside"),
    (lambda b: {"episode_successes": np.full(len(b.ends), 2, np.int8)}, "episode_successes"),
    (lambda b: {"images": np.zeros((len(b.obs), 3), np.uint8)}, "last_images"),
])
def test_a_packed_batch_that_does_not_add_up_is_refused(change, why):
    batch = packed(np.random.default_rng(3))
    bad = encode_message(dataclasses.replace(batch, **change(batch)))
    with pytest.raises(MessageError, match=why):
        decode_message(SegmentBatch, bad)


def test_packed_camera_segments_travel_as_bytes_and_come_back_as_observations():
    layout = ObsLayout((ObsField("state", "vector", (2,)), ObsField("image", "image", (1, 1, 3), uint8=True)))
    batch = packed(np.random.default_rng(4))
    pixels = lambda x: np.round(np.clip(x, 0, 1) * 255) / 255  # noqa: E731  (what a camera's bytes can say)
    batch = dataclasses.replace(batch, obs=np.concatenate([batch.obs[:, :2], pixels(batch.obs[:, 2:])], 1),
                                last_obs=np.concatenate([batch.last_obs[:, :2], pixels(batch.last_obs[:, 2:])], 1))
    wire = obswire.segment(layout, batch)
    assert wire.obs.shape[1] == 2 and wire.images.shape == (len(batch.obs), 3)
    assert wire.last_images.shape == (len(batch.env_ids), 3)
    back = obswire.decoder(SegmentBatch, layout, (D,))("k", encode_message(wire))
    np.testing.assert_allclose(back.obs, batch.obs, atol=1e-6)
    np.testing.assert_allclose(back.last_obs, batch.last_obs, atol=1e-6)
    assert back.segments()[0].images.size == 0


class Telemetry(Meter):
    def publish_span(self, *args: object, **kwargs: object) -> None:
        pass

    def event(self, *args: object) -> None:
        pass


class Sent:
    """A bus that keeps what is put on it."""

    def __init__(self) -> None:
        self.puts: list[tuple[str, object]] = []

    async def put(self, key: str, msg: object, express: bool = False) -> None:
        self.puts.append((key, msg))


class OneBatch:
    """A vectorized fleet whose batch answers from ``chunks`` in turn (``run_chunk`` as env by env); ``fail_at``:
    the group's process fails at that chunk and comes back with first observations ``FRESH``."""

    def __init__(self, chunks: list, fail_at: int = -1) -> None:
        self.chunks, self.episodes, self.at, self.fail_at = chunks, Episodes(range(N)), 0, fail_at
        self.recovered: list[tuple[int, int]] = []

    def env_ids(self, g: int) -> np.ndarray:
        return np.arange(N, dtype=np.int64)

    def given_up_env(self, env: int) -> bool:
        return False

    def saw_version(self, version: int) -> None:
        pass

    async def run_vector_chunk(self, g: int, actions: np.ndarray) -> tuple[VectorChunk | WorkerFailed, float]:
        self.at += 1
        if self.at - 1 == self.fail_at:
            return WorkerFailed("the group's process died"), 0.0
        return self.chunks[self.at - 1][2], 0.01

    async def recover(self, g: int, i: int, episode: int) -> np.ndarray:
        self.recovered.append((i, episode))
        return FRESH[i]

    async def run_chunk(self, g: int, active: list[int], actions: np.ndarray) -> tuple[list, list[float]]:
        result, latency = await self.run_vector_chunk(g, actions)
        return result.results(), [latency] * N


class Answers:
    def __init__(self, chunks: list) -> None:
        self.chunks, self.at = chunks, 0

    async def exchange(self, g: int, seq: int, env_ids: np.ndarray, obs: np.ndarray) -> ActionChunk:
        self.at += 1
        return self.chunks[self.at - 1][1]


class Iterations:
    def length(self, hosts: int) -> int:
        return 5


def test_a_vectorized_group_loop_counts_and_publishes_what_the_env_by_env_loop_does():
    """Both loops over the same chunks: the same counts, episodes and episode indices, and the same segments
    (packed on ``traj/<group>/packed``, one message per env on ``traj/<group>``)."""
    chunks = random_chunks(np.random.default_rng(11), 30)
    runs = {}
    for cls in (GroupLoop, VectorGroupLoop):
        bus, meter, stats, fleet = Sent(), Telemetry(spans=False), RolloutStats(), OneBatch(chunks)
        loop = cls(0, fleet, Answers(chunks), SegmentOutbox(bus, meter, 1 << 20, lambda: True), stats, meter, "r",
                   Iterations(), LENGTH, lambda: 1)
        for obs, *_ in chunks:
            asyncio.run(loop.step(obs))
        segments = [seg for key, msg in bus.puts for seg in (msg.segments() if isinstance(msg, SegmentBatch) else
                                                               [msg])]
        runs[cls] = (bus, meter, stats, fleet, segments)
    (bus, meter, stats, fleet, segments), (vbus, vmeter, vstats, vfleet, vsegments) = runs.values()
    assert {key for key, _ in bus.puts} == {keys.traj("r", 0)} and {key for key, _ in vbus.puts} == {
        keys.traj_packed("r", 0)}
    for name in ("sim/env_steps", "sim/episodes", "sim/segments"):
        assert meter.total(name) == vmeter.total(name) > 0, name
    assert meter.total("sim/step_busy_s") == pytest.approx(vmeter.total("sim/step_busy_s"))
    assert fleet.episodes.index == vfleet.episodes.index and stats.env_steps == vstats.env_steps
    assert [e[:6] for e in stats.episodes] == [e[:6] for e in vstats.episodes]
    assert len(segments) == len(vsegments)
    by_env = lambda segs: sorted(segs, key=lambda s: (s.env_id, s.episode, s.versions[0], len(s.obs)))  # noqa: E731
    for a, b in zip(by_env(segments), by_env(vsegments)):
        same_segment(a, b)


def test_a_vectorized_group_whose_process_died_drops_the_segments_in_progress_and_carries_the_numbering_on():
    chunks = random_chunks(np.random.default_rng(5), 12)
    bus, meter, fleet = Sent(), Telemetry(spans=False), OneBatch(chunks, fail_at=6)
    loop = VectorGroupLoop(0, fleet, Answers(chunks), SegmentOutbox(bus, meter, 1 << 20, lambda: True), RolloutStats(),
                           meter, "r", Iterations(), LENGTH, lambda: 1)
    for c in range(6):
        obs = asyncio.run(loop.step(chunks[c][0]))
    in_progress, before = len(loop.buffers), dict(fleet.episodes.index)
    assert in_progress > 0
    obs = asyncio.run(loop.step(obs))  # the process dies
    assert np.array_equal(obs, FRESH) and len(loop.buffers) == 0
    assert fleet.recovered == [(i, before[i] + 1) for i in range(N)]
    assert fleet.episodes.index == {i: before[i] + 1 for i in range(N)}
    assert meter.total("sim/worker_restarts") == 1 and meter.total("sim/partial_decisions_dropped") == in_progress
    published = sum(len(msg.obs) for _, msg in bus.puts)
    for c in range(7, 12):
        asyncio.run(loop.step(chunks[c][0]))
    assert sum(len(msg.obs) for _, msg in bus.puts) + len(loop.buffers) == published + 5 * N  # only what came after
