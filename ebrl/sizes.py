"""How large a message each data key of a run may be, from the run's shapes: one place for every receiver's bound.

A message type's ``MAX_BYTES`` (:mod:`ebrl.messages`) holds for every run, so a data key's is 256 MiB: enough for
the camera observations of hundreds of envs. A run knows far more: its envs per group, observation layout (camera
bytes included), chunk length, action dimension, the policy's latents and weights, its segment length and the
packed cap (``ebrl.sched.rollout.PACKED_BYTES``) fix the largest message that a run's own publisher can send on
each data key. :func:`largest` computes that (the encoded bytes, a little over, never under) and :class:`Bounds`
allows ``HEADROOM`` times it plus ``MARGIN`` (msgpack and Zenoh headers, a field added later).

A receiver uses them twice (:class:`ebrl.service.Service` and the services that read data keys):

* each data key's subscription refuses a payload over its key's bound (``bus/oversized``, counted and dropped)
  before it is copied out of Zenoh or decoded (:meth:`ebrl.bus.session.BusBase.fits`);
* its Zenoh session is opened with :attr:`Bounds.link` as its receive limit (``bus.max_message_bytes`` caps it):
  Zenoh stops reassembling a larger message at that many bytes and drops it, so the process's memory moves by
  about that much at most whatever arrives. Zenoh (1.10) counts nothing it drops there: such a message is seen by
  no one, only its cost is bounded.

Measured (tests/test_sizes.py): a 240 MiB observation for the quickstart's policy of 4 floats raised the peak memory
of a subscriber with the run's bound by under 2 MB; with 256 MiB as the limit, by about 250 MB, plus the copy.
"""

from __future__ import annotations

import dataclasses
import math
from dataclasses import dataclass
from typing import Any

from ebrl import messages

HEADROOM = 2  # times the largest message a run's own publisher sends
MARGIN = 64 << 10  # bytes on top: msgpack field names and array references, Zenoh's headers, a field added later
# the most bytes any message of a fixed-size type takes (a stats report, a span batch, an episode batch): every
# process receives some, so a receive limit never goes below this
FIXED_MAX = max(cls.MAX_BYTES for cls in messages.MESSAGES if cls.MAX_BYTES < messages.DATA_MAX_BYTES
                and cls not in (messages.Weights, messages.WeightsPart))
_ALIGN = 64  # ebrl.codec pads each array to this
_FRAME = 1024  # a frame's head, its msgpack header of field names and array references (a few hundred bytes)
_FLOAT, _INT = 9, 9  # msgpack bytes of a Python float (float64) and of any int


def _array(nbytes: int) -> int:
    return (nbytes + _ALIGN - 1) // _ALIGN * _ALIGN


@dataclass(frozen=True)
class Shapes:
    """What fixes a run's largest messages."""

    envs: int  # envs per group: one observation message or action chunk holds at most these
    obs_floats: int  # float32 values of one observation on the wire (the layout's fields that are not bytes)
    obs_bytes: int  # uint8 values of one observation on the wire (camera images: ObsLayout.byte_size)
    chunk: int  # K: actions per chunk
    action_dim: int
    latent: int  # float32 values of the policy's sampling state per decision (latent_shape)
    segment: int  # decisions per trajectory segment (sim.segment_length)
    packed_bytes: int  # a packed message's cap (ebrl.sched.rollout.PACKED_BYTES)
    weights: dict[str, tuple[str, tuple[int, ...]]] | None = None  # the policy's tensors (WeightsLayout.tensors)
    replay_rows: int = 0  # transitions in one ReplayRequest: an update's new decisions (train.max_pending + a segment)
    sample_rows: int = 0  # transitions in one ReplaySample (ebrl.algos.replay.batches_per_sample x batch size)

    @classmethod
    def of_run(cls, cfg: Any, info: Any, latent_shape: tuple[int, ...],
               weights: dict[str, tuple[str, tuple[int, ...]]] | None = None) -> "Shapes":
        """From a config, its env's :class:`~ebrl.envs.EnvInfo`, the policy's ``latent_shape`` and tensors."""
        from ebrl.sched.rollout import PACKED_BYTES

        from ebrl.algos.algorithm import uses_replay
        from ebrl.algos.replay import batches_per_sample

        layout = info.layout
        replay = uses_replay(cfg.algo.name)  # else no replay keys: no bound for them raises a receive limit
        per_sample = batches_per_sample(cfg.replay.batch_size, layout.size, cfg.policy.chunk * info.action_dim)
        return cls(envs=cfg.sim.envs_per_group, obs_floats=layout.size - layout.byte_size,
                   obs_bytes=layout.byte_size, chunk=cfg.policy.chunk, action_dim=info.action_dim,
                   latent=math.prod(latent_shape), segment=cfg.sim.segment_length, packed_bytes=PACKED_BYTES,
                   weights=weights, replay_rows=(cfg.train.max_pending + cfg.sim.segment_length) * replay,
                   sample_rows=per_sample * cfg.replay.batch_size * replay)


def largest(shapes: Shapes) -> dict[str, int]:
    """The encoded bytes of the largest message a run's own publisher sends on each data key (an upper bound):
    ``obs``, ``act``, ``traj``, ``packed``, ``weights`` when ``shapes.weights`` is known, ``replay_request``
    and ``replay_sample`` where the run has a replay."""
    s = shapes
    obs = 4 * s.obs_floats  # one observation's floats on the wire; its bytes are s.obs_bytes
    chunk = 4 * s.chunk * s.action_dim
    latent = 4 * s.latent
    out = {
        # env ids, observations, their bytes
        "obs": _FRAME + _array(8 * s.envs) + _array(obs * s.envs) + _array(s.obs_bytes * s.envs),
        # actions, log-probs, values, latents
        "act": _FRAME + _array(chunk * s.envs) + 2 * _array(4 * s.envs) + _array(latent * s.envs),
    }
    t = s.segment
    # TrajectorySegment: obs, actions, latents, log-probs, values, rewards, steps (float32/int32), versions (int64),
    # last_obs, images, last_images; up to T x (K + 1) episodes ended in it: a return, a length, a success each
    out["traj"] = (_FRAME + _array(obs * t) + _array(chunk * t) + _array(latent * t) + 4 * _array(4 * t)
                   + _array(8 * t) + _array(obs) + _array(s.obs_bytes * t) + _array(s.obs_bytes)
                   + t * (s.chunk + 1) * (_FLOAT + _INT + 1))
    # SegmentBatch (ebrl.sched.rollout.SegmentBuffers): as many whole segments as fit packed_bytes at the bytes a
    # decision takes in its buffers (observations as float32 there), at least one, at most a group's envs
    in_buffers = 4 * (s.obs_floats + s.obs_bytes) + chunk + latent + 4 * 4 + 8
    segments = min(s.envs, max(1, s.packed_bytes // max(1, in_buffers * t)))
    decisions = segments * t
    per_decision = obs + s.obs_bytes + chunk + latent + 4 * 4 + 8
    # per segment: env id, episode, length, end, episode offset, return, episode length, success; last_obs
    per_segment = 8 + 8 + 4 + 1 + 8 + 4 + 4 + 1 + obs + s.obs_bytes
    out["packed"] = _FRAME + 20 * _ALIGN + per_decision * decisions + per_segment * segments
    # ReplayRequest, ReplaySample: two observations (float32: the replay holds no bytes), a chunk, a reward,
    # steps, the terminal flag, a version per transition
    transition = 2 * (obs + 4 * s.obs_bytes) + chunk + 4 + 4 + 1 + 8
    if s.replay_rows:
        out["replay_request"] = _FRAME + 7 * _ALIGN + transition * s.replay_rows
        out["replay_sample"] = _FRAME + 7 * _ALIGN + transition * s.sample_rows
    if s.weights is not None:
        from ebrl.weights import PART_BYTES, SINGLE_MAX_BYTES, WeightsLayout

        total = WeightsLayout(s.weights).total_bytes
        # one Weights message under SINGLE_MAX_BYTES, else parts of PART_BYTES with part 0's manifest: either way
        # a name, a dtype, a shape and an offset (or an array reference) per tensor
        manifest = sum(len(name.encode()) + 32 + _INT * (len(shape) + 2) for name, (_, shape) in s.weights.items())
        out["weights"] = _FRAME + manifest + (total + _ALIGN * len(s.weights) if total < SINGLE_MAX_BYTES
                                              else PART_BYTES)
    return out


@dataclass(frozen=True)
class Bounds:
    """The most bytes a message on each data key of a run may take: ``HEADROOM`` x :func:`largest` + ``MARGIN``
    (``weights`` None: this receiver does not know the policy, and reads no weights)."""

    obs: int
    act: int
    traj: int
    packed: int
    weights: int | None = None
    replay_request: int | None = None  # None: the run has no replay
    replay_sample: int | None = None

    @classmethod
    def of(cls, shapes: Shapes) -> "Bounds":
        return cls(**{kind: HEADROOM * n + MARGIN for kind, n in largest(shapes).items()})

    @property
    def link(self) -> int:
        """The receive limit of the process's Zenoh session: the largest message it may receive on any key."""
        return max(FIXED_MAX, *(v for v in dataclasses.astuple(self) if v is not None)) + MARGIN


def latent_shape(policy: Any, action_dim: int) -> tuple[int, ...]:
    """The sampling state a policy of ``policy`` (a PolicySection) keeps per decision, for a receiver that builds
    no policy (the simulator): its kind's ``latent_shape_of`` (a flow policy's initial noise, one per action of
    the chunk; nothing for the Gaussian ones), a registered kind's known without importing it
    (``ebrl.policies.registry``). tests/test_sizes.py checks it against every kind's ``latent_shape``."""
    from ebrl.policies.registry import latent_shape as of_kind

    return of_kind(policy, action_dim)


def of_run(cfg: Any, info: Any, *, weights: bool) -> Bounds:
    """A run's bounds (:class:`Bounds`) for a receiver of its data keys; ``weights``: with the policy's weights
    (the policy built on torch's meta device: shapes only, no memory; torch is imported), else without."""
    tensors = None
    if weights:
        import torch

        from ebrl.policies import make_policy
        from ebrl.weights import WeightsLayout

        with torch.device("meta"):
            model = make_policy(dataclasses.replace(cfg.policy, checkpoint=""), info.layout, info.action_dim,
                                info.bounds)
        tensors = WeightsLayout.of_model(model).tensors
    return Bounds.of(Shapes.of_run(cfg, info, latent_shape(cfg.policy, info.action_dim), tensors))
