"""Sizes from shapes (issue 52): each data key's bound follows from the run's shapes (ebrl/sizes.py), the largest
message a run sends passes it, a larger one is refused before it is copied or decoded, and a 240 MiB observation
for a policy of 4 floats does not move a receiver's peak memory."""

from __future__ import annotations

import asyncio
import dataclasses
import json
import os
import subprocess
import sys
import time

import numpy as np
import pytest
import zenoh

from ebrl import config, obswire, sizes
from ebrl import keys
from ebrl.bus.memory import MemoryBus, MemoryNetwork
from ebrl.bus.session import BusOptions, zenoh_config
from ebrl.envs.obs import ObsField, ObsLayout
from ebrl.envs.worker import VectorChunk
from ebrl.messages import ActionChunk, TrajectorySegment, Weights, WeightsPart, decode_message, encode_message
from ebrl.sched import rollout
from ebrl.weights import PART_BYTES, WeightsLayout
from helpers import OWN_PROCESSES, ROOT, StatsWatcher, free_port, until, up

import oversize_peer

K, A, T = 8, 7, 32
STATE = ObsLayout.vector(4)
CAMERA = ObsLayout((ObsField("agentview", "image", (3, 64, 64), uint8=True), ObsField("state", "vector", (9,))))


def shapes(layout: ObsLayout, envs: int, latent: int = K * A, weights=None) -> sizes.Shapes:
    return sizes.Shapes(envs=envs, obs_floats=layout.size - layout.byte_size, obs_bytes=layout.byte_size, chunk=K,
                        action_dim=A, latent=latent, segment=T, packed_bytes=rollout.PACKED_BYTES, weights=weights)


def test_a_camera_configs_bounds_are_larger_than_a_state_configs_and_all_far_below_the_type_limit():
    state, camera = sizes.Bounds.of(shapes(STATE, 8)), sizes.Bounds.of(shapes(CAMERA, 8))
    assert camera.obs > 3 * state.obs and camera.traj > 8 * state.traj and camera.packed > 10 * state.packed
    raw_state, raw_camera = sizes.largest(shapes(STATE, 8)), sizes.largest(shapes(CAMERA, 8))
    assert all(raw_camera[k] > 10 * raw_state[k] for k in ("obs", "traj", "packed"))  # 12 kB of pixels per obs
    assert camera.act == state.act  # actions do not depend on what is observed
    assert state.obs < 100_000 and state.link < 2 << 20  # the quickstart's kind of run: tens of kB, not 256 MiB
    assert sizes.largest(shapes(CAMERA, 64))["obs"] > 7 * raw_camera["obs"]  # and envs per group count
    assert state.link == max(sizes.FIXED_MAX, *dataclasses.astuple(state)[:4]) + sizes.MARGIN


def _segment(layout: ObsLayout, rng) -> TrajectorySegment:
    """The largest legal segment: T decisions, every field full, T x (K + 1) episodes ended in it."""
    episodes = T * (K + 1)
    seg = TrajectorySegment(
        group=3, env_id=1 << 29, episode=1 << 40, obs=rng.random((T, layout.size), np.float32),
        actions=rng.random((T, K, A), np.float32), latents=rng.random((T, K * A), np.float32),
        logprobs=rng.random(T, np.float32), values=rng.random(T, np.float32), rewards=rng.random(T, np.float32),
        steps=np.full(T, K, np.int32), versions=np.full(T, 1 << 50, np.int64), end="truncated",
        last_obs=rng.random(layout.size, np.float32), episode_returns=list(rng.random(episodes) * 1e300),
        episode_lengths=[1 << 62] * episodes, episode_successes=[None] * episodes)
    return obswire.segment(layout, seg)


def _packed(layout: ObsLayout, envs: int, rng) -> list:
    """What a vectorized group of ``envs`` sends when every env's segment reaches its length at once."""
    buffers = rollout.SegmentBuffers(0, np.arange(envs), T)
    out = []
    for c in range(T):
        chunk = ActionChunk(group=0, seq=c, policy_version=c, actions=rng.random((envs, K, A), np.float32),
                            logprobs=rng.random(envs, np.float32), values=rng.random(envs, np.float32),
                            latents=rng.random((envs, K * A), np.float32))
        none = np.zeros(0, np.int64)
        result = VectorChunk(reward=rng.random(envs, np.float32), steps=np.full(envs, K),
                             terminated=np.zeros(envs, bool), truncated=np.zeros(envs, bool),
                             episode=np.zeros(envs, np.int64),
                             next_obs=rng.random((envs, layout.size), np.float32), ended=none,
                             final_obs=np.zeros((0, layout.size), np.float32), episode_return=np.zeros(0),
                             episode_length=none, episode_success=np.zeros(0, np.int8), busy_s=0.0, step_s=(0.0,) * K)
        out += buffers.add(rng.random((envs, layout.size), np.float32), chunk, result)
    assert out and sum(len(b.env_ids) for b in out) == envs
    return [obswire.segment(layout, b) for b in out]


@pytest.mark.parametrize("layout, envs", [(STATE, 8), (CAMERA, 8), (STATE, 4096), (CAMERA, 256)],
                         ids=["state", "camera", "state-4096-envs", "camera-256-envs"])
def test_the_largest_message_a_run_sends_on_each_key_fits_its_bound(layout, envs):
    """Real messages of the largest legal shape, encoded as the publishers encode them: each within
    ``largest`` (an upper bound, so a run never refuses its own traffic), hence within the bound."""
    rng = np.random.default_rng(0)
    tensors = {f"layer{i}.weight": ("<f4", (256, 256)) for i in range(40)}  # 10 MiB: sent in parts
    small = {"pi.weight": ("<f4", (64, 4)), "pi.bias": ("<f4", (64,))}
    for weights in (tensors, small):
        s = shapes(layout, envs, weights=weights)
        most, bounds = sizes.largest(s), sizes.Bounds.of(s)
        flat = rng.random((envs, layout.size), np.float32)
        sent = {
            "obs": [obswire.observation(layout, 0, 1 << 40, np.arange(envs) + (1 << 29), flat, time.time())],
            "act": [ActionChunk(group=0, seq=1 << 40, policy_version=1 << 50,
                                actions=rng.random((envs, K, A), np.float32), logprobs=rng.random(envs, np.float32),
                                values=rng.random(envs, np.float32), latents=rng.random((envs, K * A), np.float32))],
            "traj": [_segment(layout, rng)],
            "packed": _packed(layout, envs, rng),
        }
        arrays = {name: np.zeros(shape, dtype) for name, (dtype, shape) in weights.items()}
        total = WeightsLayout(weights).total_bytes
        if total >= 4 << 20:  # in parts: part 0 carries a full part of data and the manifest
            sent["weights"] = [WeightsPart(version=1 << 50, index=0, count=total // PART_BYTES + 1,
                                           part_bytes=PART_BYTES, total_bytes=total, created_at=time.time(),
                                           data=np.zeros(PART_BYTES, np.uint8), names=list(weights),
                                           dtypes=[d for d, _ in weights.values()],
                                           shapes=[list(shape) for _, shape in weights.values()],
                                           offsets=[1 << 40] * len(weights))]
        else:
            sent["weights"] = [Weights(version=1 << 50, params=arrays, created_at=time.time())]
        for kind, msgs in sent.items():
            for msg in msgs:
                n = len(encode_message(msg))
                assert n <= most[kind] <= getattr(bounds, kind) <= bounds.link, (kind, n, most[kind])
                decode_message(type(msg), encode_message(msg))  # legal: it decodes and checks
            assert most[kind] < 1.25 * max(len(encode_message(m)) for m in msgs) + 4096, kind  # nor far over


def test_a_simulators_latent_shape_is_the_policys_for_every_kind():
    """The simulator builds no policy: ``sizes.latent_shape`` says what each kind's ``latent_shape`` is."""
    from ebrl.policies import make_policy

    cfg = config.load(ROOT / "configs" / "quickstart.toml")
    for kind, layout in (("mlp", STATE), ("flow", STATE), ("cnn", CAMERA), ("flow", CAMERA)):
        policy = dataclasses.replace(cfg.policy, kind=kind)
        model = make_policy(policy, layout, A)
        assert tuple(model.latent_shape) == sizes.latent_shape(policy, A) or (
            int(np.prod(model.latent_shape)) == 0 == int(np.prod(sizes.latent_shape(policy, A)))), kind


def test_a_payload_over_its_keys_bound_is_counted_and_never_copied_or_decoded():
    decoded = []

    def decode(key: str, payload: bytes):
        decoded.append(len(payload))
        return payload

    class Payload:  # what Zenoh hands over: its length is known, a copy would be bytes(payload)
        def __init__(self, n):
            self.n = n

        def __len__(self):
            return self.n

        def __bytes__(self):
            raise AssertionError("an oversized payload was copied")

    async def main():
        bus = MemoryBus(MemoryNetwork())
        try:
            sub = bus.subscribe("ebrl/data/r/obs/*", decode, max_bytes=1000)
            raw = []
            bus.subscribe_raw("ebrl/data/r/weights", lambda k, p: raw.append(p), max_bytes=1000)
            sub.offer("ebrl/data/r/obs/0", Payload(1001))  # as the transport hands a sample over
            sub.offer("ebrl/data/r/obs/0", b"x" * 1000)
            await bus.put_bytes("ebrl/data/r/weights", b"y" * 1001)
            await bus.put_bytes("ebrl/data/r/weights", b"y" * 10)
            await until(lambda: raw, 10, "the small weights message")
            assert decoded == [1000] and raw == [b"y" * 10]
            assert bus.oversized == {"ebrl/data/r/obs/0": 1, "ebrl/data/r/weights": 1}
            assert sum(bus.malformed.values()) == 2
        finally:
            await bus.close()

    asyncio.run(main())


def _probe(tmp_path, limit: str) -> dict:
    """A subscriber as generation (tests/oversize_peer.py probe) receives, in order on one key: observations of
    600 kB and of seq 0 until one of seq 0 arrived (then its peak memory is read), a 240 MiB one and one of seq 2;
    its report."""
    port = free_port()
    router = zenoh.open(zenoh_config(BusOptions(mode="router", listen=[f"tcp/127.0.0.1:{port}"])))
    env = {**os.environ, "PYTHONPATH": os.pathsep.join([str(ROOT), str(ROOT / "tests")])}
    probe = subprocess.Popen([sys.executable, str(ROOT / "tests" / "oversize_peer.py"), "probe",
                              str(ROOT / "configs" / "quickstart.toml"), f"tcp/127.0.0.1:{port}", limit],
                             stdout=subprocess.PIPE, text=True, env=env)
    sender = zenoh.open(zenoh_config(BusOptions(mode="client", connect=[f"tcp/127.0.0.1:{port}"], listen=[])))
    key = keys.obs("quickstart", 0)
    try:
        first = oversize_peer.observation(24 * 8, 0)
        ready = []
        import threading

        reader = threading.Thread(target=lambda: ready.append(probe.stdout.readline()), daemon=True)
        reader.start()
        deadline = time.monotonic() + 120  # a bound for a hang (the probe describes the env first), not a window
        block = zenoh.CongestionControl.BLOCK
        while reader.is_alive():  # until the probe has one (its subscription reached the router)
            assert time.monotonic() < deadline and probe.poll() is None, "the probe never received an observation"
            sender.put(key, oversize_peer.observation(600_000, 1), congestion_control=block)
            sender.put(key, first)
            reader.join(0.2)
        assert ready[0].startswith("ready"), ready
        sender.put(key, oversize_peer.observation(240 << 20, 1), congestion_control=block)
        sender.put(key, oversize_peer.observation(24 * 8, 2), congestion_control=block)
        out, _ = probe.communicate(timeout=120)
    finally:
        if probe.poll() is None:
            probe.kill()
        sender.close()
        router.close()
    assert probe.returncode == 0, out
    return json.loads(out.splitlines()[-1])


def test_a_240_mib_observation_for_a_policy_of_4_floats_does_not_move_a_receivers_peak_memory(tmp_path):
    """With the run's bounds (as gen's): its peak memory (VmHWM) moves by less than 10 MB; the 240 MiB one is dropped
    by Zenoh at the run's receive limit (uncounted: Zenoh counts nothing there), those of 600 kB, under that limit
    but over the observations' bound, are counted as oversized; the legal ones arrive, in order."""
    got = _probe(tmp_path, "run")
    moved_mb = (got["after_kb"] - got["before_kb"]) / 1024
    print(f"peak memory moved by {moved_mb:.1f} MB (receive limit {got['link_bytes']} bytes)")
    assert moved_mb < 10, got
    assert got["oversized"] >= 1 and got["malformed"] == got["oversized"] and got["seqs"] == [0, 2], got
    assert got["link_bytes"] < 2 << 20


def test_without_the_runs_bounds_the_same_observation_costs_hundreds_of_mb(tmp_path):
    """The measurement can fail: with bus.max_message_bytes alone (256 MiB, as before), the same 240 MiB observation
    is reassembled, copied and decoded, and the receiver's peak memory moves by over 200 MB."""
    got = _probe(tmp_path, "bus")
    moved_mb = (got["after_kb"] - got["before_kb"]) / 1024
    print(f"peak memory moved by {moved_mb:.1f} MB without the run's bounds")
    assert moved_mb > 200 and got["seqs"] == [0, 1, 2] and got["oversized"] == 0, got


@pytest.mark.slow  # in the fast suite: tests/test_untrusted_sim.py, every case in one run
def test_an_insider_sending_a_240_mib_observation_with_the_simulators_credential_moves_nothing(tmp_path):
    """A live quickstart run with its real settings: a process signed in with sim/0's own line (as its launcher hands
    it) sends an observation of 600 kB and 64 bytes of junk, then one of 240 MiB and junk again. The run finishes
    every iteration and nothing restarts; gen reports the 600 kB one as bus/oversized (the 240 MiB one Zenoh drops at
    gen's receive limit, uncounted: only its cost is bounded) and each junk as malformed. Gen's and train's peak
    memory (VmHWM), read before the 240 MiB one and again once gen counted the junk after it, move by less than
    10 MB. (The 600 kB one, under gen's receive limit and over its key's bound, is reassembled by Zenoh and dropped
    before it is copied: about 19 MB of gen's peak once, measured apart; that is why it goes first.)"""
    env = {**os.environ, "PYTHONPATH": os.pathsep.join([str(ROOT), str(ROOT / "tests")])}
    with up(tmp_path, "configs/quickstart.toml", "run.iterations=30", 'viz.rerun="off"', OWN_PROCESSES,
            name="oversize") as run:
        run.wait_for_line("all services live", 300)
        with StatsWatcher(run) as stats:
            got = oversize_peer.attack(run, stats, env)
            code = run.wait(300)
    first, big, pids, before, after = (got[k] for k in ("first", "big", "pids", "before", "after"))
    assert first["routers"] == 1 and big["routers"] == 1
    assert [p["bytes"] > (240 << 20) for p in first["puts"] + big["puts"]] == [False, False, True, False], big
    print(f"240 MiB put took {big['puts'][0]['seconds']} s; peak memory (kB) before {before}, after {after}")
    assert code == 0, run.output[-4000:]
    assert set(pids) == {"gen", "train"}
    for role in ("gen", "train"):  # measured: gen +1.3 MB and +0.5 MB for two of them, train +0.1 MB
        assert (after[role] - before[role]) / 1024 < 10, (role, before, after)
    assert stats.latest("train/0", "train/policy_version") == 30
    summary = json.loads((run.run_dir / "summary.json").read_text())
    assert summary["restarts"] == {}, summary
    assert "restart" not in run.output
    assert stats.latest("gen/0", "bus/oversized") == 1 and stats.latest("train/0", "bus/oversized") == 0
