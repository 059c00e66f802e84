"""Weights over the bus: whole and in parts, bit-identical; incomplete versions never handed out; late joiners.

Every test runs over Zenoh (two peers on loopback) and over the in-memory bus (``kind``)."""

import asyncio
import contextlib

import msgpack
import numpy as np
import pytest

from ebrl import keys
from ebrl.messages import StatsReport, Weights, WeightsPart, decode_message, encode_message
import ebrl.weights as weights_module
from ebrl.weights import ALIGN, WeightsPublisher, WeightsReceiver
from helpers import BUS_KINDS, bus_pair, until

RUN = "w"


def model(scale: int = 1) -> dict[str, np.ndarray]:
    """A state dict with the awkward cases: several dtypes, a 0-d array, an empty one, odd byte counts."""
    rng = np.random.default_rng(scale)
    return {
        "enc.weight": rng.standard_normal((64 * scale, 33)).astype(np.float32),
        "enc.bias": rng.standard_normal(33).astype(np.float16),
        "steps": np.array(7, dtype=np.int64),
        "mask": rng.random(13) > 0.5,
        "empty": np.zeros((0, 5), np.float32),
        "head.weight": rng.standard_normal((33, 7)).astype(np.float64),
    }


def assert_identical(got: dict[str, np.ndarray], want: dict[str, np.ndarray]) -> None:
    assert list(got) == list(want)
    for name, array in want.items():
        assert got[name].dtype == array.dtype and got[name].shape == array.shape, name
        assert got[name].tobytes() == array.tobytes(), name


@pytest.fixture(params=BUS_KINDS)
def kind(request):
    return request.param


@contextlib.asynccontextmanager
async def two_peers(kind: str):
    """A publishing and a receiving bus, connected; ``pair.settled()`` returns once the receiver's
    subscriptions so far are known to the publisher."""
    async with bus_pair(kind) as pair:
        yield pair.sender, pair.receiver, pair


def encoded_parts(version: int, arrays: dict[str, np.ndarray], part_bytes: int, created_at: float = 1.0) -> list[bytes]:
    """The parts a publisher sends, built here independently of it."""
    offsets, total = [], 0
    for array in arrays.values():
        offsets.append(total)
        total += -(-array.nbytes // ALIGN) * ALIGN
    buffer = np.zeros(total, np.uint8)
    for array, offset in zip(arrays.values(), offsets):
        buffer[offset:offset + array.nbytes] = array.reshape(-1).view(np.uint8)
    count = -(-total // part_bytes)
    parts = []
    for index in range(count):
        part = WeightsPart(version=version, index=index, count=count, part_bytes=part_bytes, total_bytes=total,
                           created_at=created_at, data=buffer[index * part_bytes:(index + 1) * part_bytes])
        if index == 0:
            part.names = list(arrays)
            part.dtypes = [a.dtype.str for a in arrays.values()]
            part.shapes = [list(a.shape) for a in arrays.values()]
            part.offsets = offsets
        parts.append(encode_message(part))
    return parts


def test_small_weights_go_whole_and_large_ones_in_parts_bit_identical(kind):
    async def scenario():
        async with two_peers(kind) as (pub_bus, sub_bus, pair):
            wake = asyncio.Event()
            receiver = WeightsReceiver(sub_bus, RUN, notify=wake)
            whole = sub_bus.subscribe(keys.weights(RUN), Weights, policy="latest", capacity=1)  # today's gen
            publisher = WeightsPublisher(pub_bus, RUN)
            await pair.settled()

            small = model()
            stats = await publisher.publish(1, small)
            assert (stats.sent, stats.mode, stats.parts) == (True, "whole", 1)
            await asyncio.wait_for(wake.wait(), 10)
            got = receiver.take_newer(0)
            assert got.version == 1 and receiver.take_newer(0) is None  # taken once
            assert_identical(got.params, small)
            _, legacy = await asyncio.wait_for(whole.next(), 10)
            assert legacy.version == 1

            large = {**model(), "big.weight": np.arange(3_000_003, dtype=np.float32).reshape(3, -1)}  # 12 MB
            stats = await publisher.publish(2, large)
            assert (stats.sent, stats.mode, stats.parts) == (True, "parts", 3)
            await until(lambda: receiver.version == 2, 10, "version 2")
            got = receiver.take_newer(1)
            assert got.version == 2 and got.created_at > 0
            assert_identical(got.params, large)
            assert got.params["big.weight"].flags.writeable  # loads without a defensive copy
            assert receiver.completed == 2 and receiver.discarded == 0 and not sub_bus.malformed
            assert len(whole) == 0  # a subscriber of the whole-message key never sees parts
            publisher.close()

    asyncio.run(scenario())


def test_an_incomplete_version_is_never_handed_out_and_a_newer_one_supersedes_it(kind):
    async def scenario():
        async with two_peers(kind) as (pub_bus, sub_bus, pair):
            receiver = WeightsReceiver(sub_bus, RUN)
            await pair.settled()
            key = keys.weights_parts(RUN)
            old, new = model(1), model(2)
            old_parts, new_parts = encoded_parts(5, old, 1024), encoded_parts(6, new, 1024)
            assert len(old_parts) > 3
            for payload in old_parts[:-1]:  # the last part of v5 never comes
                await pub_bus.put_bytes(key, payload)
            await asyncio.sleep(0.3)
            assert receiver.take_newer(-1) is None and receiver.version == -1
            for payload in reversed(new_parts):  # order does not matter; part 0 (the manifest) comes last
                await pub_bus.put_bytes(key, payload)
            await until(lambda: receiver.version == 6, 10, "version 6")
            await pub_bus.put_bytes(key, old_parts[-1])  # v5's missing part, too late
            await pub_bus.put_bytes(key, new_parts[1])  # a duplicate of a complete version
            await until(lambda: receiver.stale == 2, 10, "the late parts to be counted")
            got = receiver.take_newer(-1)
            assert got.version == 6 and receiver.take_newer(-1) is None
            assert_identical(got.params, new)
            assert receiver.discarded == 1 and receiver.completed == 1 and not sub_bus.malformed

    asyncio.run(scenario())


def test_parts_of_a_version_number_sent_twice_never_mix(kind):
    async def scenario():
        async with two_peers(kind) as (pub_bus, sub_bus, pair):
            receiver = WeightsReceiver(sub_bus, RUN)
            await pair.settled()
            key = keys.weights_parts(RUN)
            dying, restarted = model(1), {name: a + 1 if a.dtype != bool else ~a for name, a in model(1).items()}
            for payload in encoded_parts(4, dying, 1024, created_at=10.0)[:-1]:  # train died before its last part
                await pub_bus.put_bytes(key, payload)
            for payload in encoded_parts(4, restarted, 1024, created_at=20.0)[1:]:  # part 0 comes last
                await pub_bus.put_bytes(key, payload)
            await asyncio.sleep(0.3)
            assert receiver.version == -1  # the restarted train's part 0 is missing: not complete yet
            await pub_bus.put_bytes(key, encoded_parts(4, restarted, 1024, created_at=20.0)[0])
            await until(lambda: receiver.version == 4, 10, "version 4")
            assert_identical(receiver.take_newer(-1).params, restarted)
            assert receiver.discarded == 1

    asyncio.run(scenario())


def test_malformed_parts_are_counted_and_dropped(kind):
    async def scenario():
        async with two_peers(kind) as (pub_bus, sub_bus, pair):
            receiver = WeightsReceiver(sub_bus, RUN)
            await pair.settled()
            key = keys.weights_parts(RUN)
            arrays = model()
            good = encoded_parts(3, arrays, 4096)

            def tampered(payload: bytes, **changes) -> bytes:
                part = decode_message(WeightsPart, payload)
                for name, value in changes.items():
                    setattr(part, name, value)
                return encode_message(part)

            bad = [
                b"\xc1garbage",
                msgpack.packb({"v": 1, "version": 3}),
                encode_message(StatsReport(run="w", service="s", instance=0, time=0.0, seq=0, metrics={})),
                tampered(good[1], data=np.zeros(5, np.uint8)),  # wrong length for its place
                tampered(good[1], index=99),
                tampered(good[1], count=1),
                tampered(good[0], offsets=[0, 0, 0, 0, 0, 10**9]),  # an array outside the buffer
                tampered(good[0], dtypes=["<f4", "|O", "<i8", "|b1", "<f4", "<f8"]),
                tampered(good[0], names=["a", "a", "b", "c", "d", "e"]),
                tampered(good[0], shapes=[[64, 33]]),
                tampered(good[0], dtypes=["<f4", "bogus", "<i8", "|b1", "<f4", "<f8"]),
                tampered(good[0], shapes=[[10**12, 10**12], [33], [], [13], [0, 5], [33, 7]]),
            ]
            for payload in bad:
                await pub_bus.put_bytes(key, payload)
            await pub_bus.put_bytes(keys.weights(RUN), b"\x93not a weights map")
            for payload in good:
                await pub_bus.put_bytes(key, payload)
            await until(lambda: receiver.version == 3, 10, "the good version")
            assert sub_bus.malformed[key] == len(bad) and sub_bus.malformed[keys.weights(RUN)] == 1
            assert_identical(receiver.take_newer(-1).params, arrays)

    asyncio.run(scenario())


def test_a_late_receiver_gets_a_complete_version_by_query(kind):
    async def scenario():
        async with two_peers(kind) as (pub_bus, sub_bus, pair):
            publisher = WeightsPublisher(pub_bus, RUN, part_bytes=64 << 10, single_max_bytes=256 << 10)
            await pair.settled()
            assert await WeightsReceiver(sub_bus, RUN).request(timeout=1.0) is False  # nothing published yet
            large = model(40)  # 700 KB: 11 parts
            stats = await asyncio.gather(publisher.publish(7, model(39)), publisher.publish(8, large))
            assert stats[1].sent and stats[1].mode == "parts" and publisher.published + publisher.superseded == 2
            receiver = WeightsReceiver(sub_bus, RUN)  # joins after the last publish
            await pair.settled()
            assert await receiver.request(timeout=10.0) is True
            got = receiver.take_newer(-1)
            assert got.version == 8 and receiver.discarded == 0
            assert_identical(got.params, large)

            await publisher.publish(9, model())  # small: answered with the one message, on its own key
            assert await receiver.request(timeout=10.0) is True
            assert_identical(receiver.take_newer(8).params, model())
            replies = await sub_bus.get(keys.weights(RUN), timeout=5.0)  # how today's gen asks
            assert [(key, decode_message(Weights, payload).version) for key, payload in replies] \
                == [(keys.weights(RUN), 9)]
            publisher.close()

    asyncio.run(scenario())


def test_the_receiver_reuses_a_buffer_only_once_nothing_reads_it(kind):
    async def scenario():
        async with two_peers(kind) as (pub_bus, sub_bus, pair):
            receiver = WeightsReceiver(sub_bus, RUN)
            publisher = WeightsPublisher(pub_bus, RUN, part_bytes=4096, single_max_bytes=0)
            await pair.settled()

            def arrays(version: int) -> dict[str, np.ndarray]:
                out = model(2)  # the same size every version, so a buffer fits the next one
                out["enc.weight"] += version
                return out

            async def receive(version: int) -> Weights:
                await publisher.publish(version, arrays(version))
                await until(lambda: receiver.version == version, 10, f"version {version}")
                return receiver.take_newer(version - 1)

            def address(weights: Weights) -> int:
                return weights.params["enc.weight"].ctypes.data

            held = await receive(1)
            second = await receive(2)
            assert address(second) != address(held)  # v1 is still being read: not overwritten
            reused_at = address(second)
            del second
            third = await receive(3)
            assert address(third) == reused_at  # v2's buffer, free again
            assert_identical(held.params, arrays(1))
            assert_identical(third.params, arrays(3))
            publisher.close()

    asyncio.run(scenario())


@pytest.mark.parametrize("whole", [True, False], ids=["whole", "parts"])
def test_a_receiver_put_ahead_of_the_trainer_by_a_forged_version_goes_back_to_the_trainers(kind, whole, monkeypatch):
    """Issue 34: one plausible forged version (the trainer's own tensors, its version + 60) puts the receiver
    ahead of the trainer, whose reports say it is at v1; after 3 such reports the receiver asks the trainer for
    its newest and hands it out although its number is older (counted in ``resets``), then follows it again."""
    monkeypatch.setattr(weights_module, "AHEAD_S", 0.2)

    async def scenario():
        async with two_peers(kind) as (pub_bus, sub_bus, pair):
            receiver = WeightsReceiver(sub_bus, RUN)
            follower = asyncio.create_task(receiver.follow_trainer())
            sizes = {"part_bytes": 1024, "single_max_bytes": (4 << 20) if whole else 0}
            publisher = WeightsPublisher(pub_bus, RUN, **sizes)
            await pair.settled()
            arrays = model()
            assert (await publisher.publish(1, arrays)).mode == ("whole" if whole else "parts")
            await until(lambda: receiver.version == 1, 10, "v1")
            assert receiver.take_newer(0).version == 1
            forger = WeightsPublisher(pub_bus, RUN, **sizes)  # a peer that only puts (no answer to queries)
            await forger.publish(61, arrays)
            forger.close()
            await until(lambda: receiver.version == 61, 10, "the forged v61")
            current = receiver.take_newer(1).version  # the taker acts with v61 now

            async def report(version: int) -> None:
                await pub_bus.put(keys.stats(RUN, "train", 0), StatsReport(
                    run=RUN, service="train", instance=0, time=0.0, seq=0, metrics={"train/policy_version": version}))

            for _ in range(2):
                await report(1)
                await asyncio.sleep(0.15)
            assert receiver.resets == 0 and receiver.take_newer(current) is None  # not yet
            await report(1)
            await until(lambda: receiver.resets == 1 and receiver.version == 1, 10, "the reset to the trainer's v1")
            got = receiver.take_newer(current)
            assert got is not None and got.version == 1  # older than the taker's v61, handed out all the same
            assert_identical(got.params, arrays)
            await publisher.publish(2, arrays)
            await until(lambda: receiver.version == 2, 10, "v2")
            assert receiver.take_newer(1).version == 2 and receiver.counters()["version_resets"] == 1
            await report(2)  # at the trainer's version: nothing happens
            await asyncio.sleep(0.3)
            assert receiver.resets == 1 and not sub_bus.malformed
            follower.cancel()
            publisher.close()

    asyncio.run(scenario())
