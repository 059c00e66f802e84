"""Camera images travel on the bus as bytes (issue 38): ObsLayout.to_wire / from_wire, the messages' ``images``
fields, ebrl.obswire's split and join, and a real run whose observations and segments carry uint8."""

from __future__ import annotations

import threading
from pathlib import Path

import numpy as np
import pytest
import zenoh

from ebrl import obswire
from ebrl import keys
from ebrl.envs.obs import ObsField, ObsLayout, tokenize
from ebrl.messages import MessageError, Observation, TrajectorySegment, decode_message, encode_message
from ebrl.testing import Run, StatsWatcher, run_session_config

TESTS = Path(__file__).resolve().parent
ROOT = TESTS.parent
LAYOUT = ObsLayout((ObsField("joints", "vector", (3,)), ObsField("cam", "image", (3, 8, 6), uint8=True),
                    ObsField("task", "tokens", (16,)), ObsField("wrist", "image", (1, 4, 4), uint8=True)))
FLOAT_IMAGES = ObsLayout((ObsField("depth", "image", (1, 4, 4)), ObsField("joints", "vector", (3,))))


def observations(n: int, rng: int = 0) -> np.ndarray:
    """``n`` flat observations of LAYOUT as an env side makes them: pixels / 255, tokens, any floats."""
    rng = np.random.default_rng(rng)
    return np.stack([LAYOUT.pack({"joints": rng.normal(size=3), "task": tokenize("pick the cube"),
                                  "cam": rng.integers(0, 256, (3, 8, 6)).astype(np.float32) / np.float32(255),
                                  "wrist": rng.integers(0, 256, (1, 4, 4)).astype(np.float32) / np.float32(255)})
                     for _ in range(n)])


def test_uint8_fields_travel_as_bytes_and_come_back_exactly():
    obs = observations(5)
    floats, pixels = LAYOUT.to_wire(obs)
    assert floats.dtype == np.float32 and floats.shape == (5, 3 + 16)
    assert pixels.dtype == np.uint8 and pixels.shape == (5, 3 * 8 * 6 + 16) and LAYOUT.byte_size == 160
    assert np.array_equal(LAYOUT.from_wire(floats, pixels), obs)  # bit for bit
    with pytest.raises(ValueError, match="float and .* byte values"):
        LAYOUT.from_wire(floats[:, :-1], pixels)


def test_a_layout_without_uint8_fields_is_unchanged_on_the_bus():
    """Float images (a user's 3-d Box, any scale) are not quantized: only fields read from bytes are."""
    obs = np.random.default_rng(0).normal(size=(4, FLOAT_IMAGES.size)).astype(np.float32)
    floats, pixels = FLOAT_IMAGES.to_wire(obs)
    assert floats is obs or np.array_equal(floats, obs)
    assert pixels.shape == (4, 0) and FLOAT_IMAGES.byte_size == 0
    message = obswire.observation(FLOAT_IMAGES, 0, 1, np.arange(4), obs, 0.0)
    assert message.images.size == 0 and message.obs is obs


def test_the_layout_remembers_which_fields_are_bytes():
    again = ObsLayout.from_dict(LAYOUT.to_dict())
    assert again == LAYOUT and again.byte_size == 160
    old = [{"name": "image", "kind": "image", "shape": [3, 8, 8]}]  # a checkpoint from before the flag
    assert ObsLayout.from_dict(old).fields[0].uint8 is False


def test_an_observation_message_is_a_quarter_of_the_size_and_decodes_to_the_same_observations():
    obs = observations(4)
    wire = encode_message(obswire.observation(LAYOUT, 2, 7, np.arange(4), obs, 1.5))
    plain = encode_message(Observation(group=2, seq=7, env_ids=np.arange(4), obs=obs, sent_at=1.5))
    assert len(wire) < 0.45 * len(plain)
    message = obswire.decoder(Observation, LAYOUT, (LAYOUT.size,))("k", wire)
    assert np.array_equal(message.obs, obs) and message.images.size == 0 and message.seq == 7


def segment(obs: np.ndarray) -> TrajectorySegment:
    t = len(obs) - 1
    return TrajectorySegment(group=0, env_id=3, episode=0, obs=obs[:t], actions=np.zeros((t, 2, 1), np.float32),
                             latents=np.zeros((t, 0), np.float32), logprobs=np.zeros(t, np.float32),
                             values=np.zeros(t, np.float32), rewards=np.ones(t, np.float32),
                             steps=np.full(t, 2, np.int32), versions=np.zeros(t, np.int64), end="cut",
                             last_obs=obs[t], episode_returns=[], episode_lengths=[])


def test_a_segment_travels_with_its_images_as_bytes():
    obs = observations(6, rng=1)
    wire = obswire.segment(LAYOUT, segment(obs))
    assert wire.images.shape == (5, 160) and wire.last_images.shape == (160,) and wire.obs.shape == (5, 19)
    back = obswire.decoder(TrajectorySegment, LAYOUT, (LAYOUT.size,))("k", encode_message(wire))
    assert np.array_equal(back.obs, obs[:5]) and np.array_equal(back.last_obs, obs[5])
    assert back.images.size == 0 and back.last_images.size == 0


def test_bytes_that_do_not_fit_the_receivers_layout_are_a_malformed_message():
    obs = observations(3)
    as_floats = ObsLayout(tuple(ObsField(f.name, f.kind, f.shape) for f in LAYOUT.fields))  # the same, no bytes
    with_bytes = encode_message(obswire.observation(LAYOUT, 0, 1, np.arange(3), obs, 0.0))
    without = encode_message(Observation(group=0, seq=1, env_ids=np.arange(3), obs=obs, sent_at=0.0))
    with pytest.raises(MessageError, match="19 float and 160 byte values"):
        obswire.decoder(Observation, as_floats, (as_floats.size,))("k", with_bytes)
    with pytest.raises(MessageError, match="179 float and 0 byte values"):
        obswire.decoder(Observation, LAYOUT, (LAYOUT.size,))("k", without)
    rows = obswire.observation(LAYOUT, 0, 1, np.arange(3), obs, 0.0)
    rows.images = rows.images[:2]
    with pytest.raises(MessageError, match="2 rows of bytes for 3 observations"):
        decode_message(Observation, encode_message(rows))
    bad = obswire.segment(LAYOUT, segment(observations(4)))
    bad.last_images = bad.last_images[:-1]
    with pytest.raises(MessageError, match="last_images"):
        decode_message(TrajectorySegment, encode_message(bad))


def test_a_real_runs_camera_observations_and_segments_are_bytes_on_the_bus(tmp_path, monkeypatch):
    """A user's Dict env with a 16x16x3 camera (tests/user_envs.py): what sim publishes carries the image as 768
    bytes per observation, and the run trains on it."""
    monkeypatch.setenv("PYTHONPATH", str(TESTS))
    seen: dict[str, list] = {"obs": [], "traj": []}
    lock = threading.Lock()

    def keep(kind, cls):
        def on_sample(sample: zenoh.Sample) -> None:
            with lock:
                seen[kind].append(decode_message(cls, sample.payload.to_bytes()))
        return on_sample

    with Run(ROOT / "configs" / "quickstart.toml", "run.iterations=2", 'env.id="user_envs:GoalImage-v0"',
             'policy.kind="cnn"', "policy.channels=[8]", "policy.embed_dim=32", "sim.envs_per_group=2",
             "train.batch_size=64", name="bytes", out_dir=tmp_path / "runs") as run, StatsWatcher(run) as stats:
        session = zenoh.open(run_session_config(run, role="launcher"))  # an observer may not read the data
        subscribers = [session.declare_subscriber(keys.obs(run.name), keep("obs", Observation)),
                       session.declare_subscriber(keys.traj(run.name), keep("traj", TrajectorySegment))]
        assert run.wait(300) == 0, run.tail()
        for sub in subscribers:
            sub.undeclare()
        session.close()
    assert stats.latest("train/0", "train/policy_version") == 2
    with lock:
        assert seen["obs"] and seen["traj"]
        for message in seen["obs"]:
            assert message.images.dtype == np.uint8 and message.images.shape == (len(message.env_ids), 768)
            assert message.obs.shape == (len(message.env_ids), 2 + 2 + 16)  # goal, robot/position, task
        for message in seen["traj"]:
            assert message.images.shape == (len(message.obs), 768) and message.last_images.shape == (768,)
