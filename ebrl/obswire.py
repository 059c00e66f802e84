"""Observations on the bus: camera images as bytes.

An observation is one flat float32 vector per env (:mod:`ebrl.envs.obs`), but a field read from uint8 pixels
(``ObsField.uint8``) travels as those bytes: a quarter of the size for what dominates a camera observation.
The sim service splits what it publishes (:func:`observation`, :func:`segment`); gen and train decode with
:func:`decoder`, which joins the two parts back into the flat observations their policy takes, so nothing past
the bus sees the difference. A message whose parts do not fit the receiver's layout is malformed: counted and
dropped like any other.
"""

from __future__ import annotations

import dataclasses
from typing import Callable, TypeVar

import numpy as np

from ebrl.envs.obs import ObsLayout
from ebrl.messages import MessageError, Observation, SegmentBatch, TrajectorySegment, accept, decode_message

M = TypeVar("M", Observation, TrajectorySegment, SegmentBatch)
S = TypeVar("S", TrajectorySegment, SegmentBatch)


def observation(layout: ObsLayout, group: int, seq: int, env_ids: np.ndarray, obs: np.ndarray,
                sent_at: float) -> Observation:
    """A group's observations ``[E, *obs_shape]`` as the message sim publishes."""
    if not layout.byte_size:
        return Observation(group=group, seq=seq, env_ids=env_ids, obs=obs, sent_at=sent_at)
    floats, pixels = layout.to_wire(obs)
    return Observation(group=group, seq=seq, env_ids=env_ids, obs=floats, sent_at=sent_at, images=pixels)


def segment(layout: ObsLayout, seg: S) -> S:
    """A segment (or a group's packed segments) as sim publishes it: the uint8 fields of ``obs`` and
    ``last_obs`` as bytes."""
    if not layout.byte_size:
        return seg
    floats, pixels = layout.to_wire(seg.obs)
    if isinstance(seg, SegmentBatch):  # a last observation per segment
        last, last_pixels = layout.to_wire(seg.last_obs)
        return dataclasses.replace(seg, obs=floats, images=pixels, last_obs=last, last_images=last_pixels)
    last, last_pixels = layout.to_wire(seg.last_obs[None])
    return dataclasses.replace(seg, obs=floats, images=pixels, last_obs=last[0], last_images=last_pixels[0])


def decoder(cls: type[M], layout: ObsLayout, obs_shape: tuple[int, ...]) -> Callable[[str, bytes], M]:
    """``(key, payload) -> message`` for ``bus.subscribe``: decode, then join the bytes back into observations of
    ``obs_shape`` (MessageError, dropped and counted, for parts that do not fit ``layout``). Its ``local`` does
    the same for a message handed over by reference in the process (``ebrl.bus.local``)."""

    def join(msg: M) -> M:
        if not layout.byte_size and not msg.images.size:
            return msg
        try:
            obs = layout.from_wire(msg.obs, msg.images).reshape(len(msg.obs), *obs_shape)
            if isinstance(msg, Observation):
                return dataclasses.replace(msg, obs=obs, images=np.zeros((0, 0), np.uint8))
            if isinstance(msg, SegmentBatch):
                last = layout.from_wire(msg.last_obs, msg.last_images).reshape(len(msg.last_obs), *obs_shape)
                return dataclasses.replace(msg, obs=obs, last_obs=last, images=np.zeros((0, 0), np.uint8),
                                           last_images=np.zeros((0, 0), np.uint8))
            last = layout.from_wire(msg.last_obs[None], msg.last_images[None]).reshape(obs_shape)
            return dataclasses.replace(msg, obs=obs, last_obs=last, images=np.zeros((0, 0), np.uint8),
                                       last_images=np.zeros(0, np.uint8))
        except ValueError as exc:
            raise MessageError(f"{cls.__name__}: {exc}") from None

    def decode(_key: str, payload: bytes) -> M:
        return join(decode_message(cls, payload))

    decode.local = lambda _key, msg: join(accept(cls, msg))  # type: ignore[attr-defined]
    return decode
