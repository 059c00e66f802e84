"""The learner of one training rank (Sample Factory's ``Learner``): segments in, updates, versioned weights.

It holds the policy, PPO/GRPO and the bounded collector, and the rules that keep versions honest:

* a segment is taken only if its shapes match the policy and it was acted by a version this learner
  published (``versions <= version``); a bad one is dropped, counted;
* versions never go back or repeat: a restart resumes from the run's latest checkpoint and, when the
  launcher says a newer version was published before (``procenv.version_floor``), continues after it;
* a learner stopped to start again (a new GPU share) hands the segments it had not trained on over to
  the next one (``RUN_DIR/train-pending.msgpack``, fsynced, one checked record per segment), which takes
  them over once: a file torn by a kill loses only its torn record.

No bus and no event loop here: the train service (``services/train.py``) drives it, and with several
ranks the choreography of ``ebrl.algos.parallel`` decides who learns from what.
"""

from __future__ import annotations

import collections
import contextlib
import logging
import os
import struct
import time
import zlib
from pathlib import Path
from typing import Any, BinaryIO, Callable, Iterable

import msgpack
import numpy as np
import torch

from ebrl import devices
from ebrl.algos import checkpoint
from ebrl.algos.grpo import GroupCollector
from ebrl.algos.parallel import Command, DataParallel, shards
from ebrl.algos.ppo import PPO, Batch, SegmentCollector
from ebrl.messages import MessageError, TrajectorySegment, decode_message, encode_message
from ebrl.policies import make_policy, save_checkpoint, state_arrays
from ebrl.policies.checkpoint import portable_metadata, remove_stale_temporaries
from ebrl.recorder import Telemetry

log = logging.getLogger(__name__)

POLICY_FILE = "policy.safetensors"  # the trained policy, for `--set policy.checkpoint=RUN_DIR/policy.safetensors`
HANDOVER_FILE = "train-pending.msgpack"  # segments a stopping train leaves to the next one (RUN_DIR)
HANDOVER_MAGIC = b"EBRL-HANDOVER/1\n"  # then records: <u32 length><u32 crc32 of the payload><payload>
_RECORD = struct.Struct("<II")


class Learner:
    """One rank's policy, optimiser and pending data; ``version`` is the newest policy version it made."""

    def __init__(self, cfg: Any, info: Any, max_staleness: int, telemetry: Telemetry, run_dir: str,
                 rank: int = 0, world: int = 1):
        self.cfg, self.telemetry, self.run_dir, self.rank, self.world = cfg, telemetry, run_dir, rank, world
        torch.manual_seed(cfg.run.seed)
        self.device = devices.rank_device(cfg.train.device, "train.device", rank)
        self.obs_shape = info.obs_shape
        self.action_shape = (cfg.policy.chunk, info.action_dim)
        self.model = make_policy(cfg.policy, info.layout, info.action_dim).to(self.device)  # before the optimizer
        self.portable = portable_metadata(cfg.policy, cfg.env, info)  # every policy file: loadable on its own
        self.latent_shape = tuple(self.model.latent_shape)
        self.ppo = PPO(self.model, cfg.algo, cfg.train.lr, seed=cfg.run.seed)
        self.version = self.saved_version = 0
        self.dp: DataParallel | None = None
        collector = GroupCollector if cfg.algo.name == "grpo" else SegmentCollector
        self.collector = collector(cfg.algo, cfg.train.max_pending, max_staleness, telemetry.count)
        self.returns: collections.deque[float] = collections.deque(maxlen=20)
        self.staleness_hist = np.zeros(max_staleness + 1, dtype=np.int64)  # decisions per lag
        self.arrays: dict[str, np.ndarray] = {}  # the full weights rank 0 publishes
        self.train_state: tuple[int, dict, dict] | None = None  # sharded: (version, model, optimizer) gathered

    def join(self) -> None:
        """With several ranks: join the training group (blocks until every rank joined; every rank then
        holds rank 0's weights)."""
        self.dp = DataParallel(self.model, self.ppo.optimizer, self.rank, self.world,
                               shard=self.cfg.train.parallel == "fsdp", device=self.device)
        self.ppo.net, self.ppo.optimizer = self.dp.net, self.dp.optimizer

    @property
    def sharded(self) -> bool:
        return self.dp is not None and self.dp.shard

    @property
    def ready(self) -> bool:
        return self.collector.ready_steps >= self.cfg.train.batch_size

    def accept(self, seg: TrajectorySegment, malformed: Callable[[Exception], None]) -> bool:
        """Check one segment against this policy and add it to the collector (False: dropped, counted). Its own
        consistency (every per-decision field T long, finite values) was checked when it was decoded
        (``TrajectorySegment.check``)."""
        if seg.obs.shape[1:] != self.obs_shape or seg.actions.shape[1:] != self.action_shape \
                or seg.latents.shape[1:] != self.latent_shape:
            malformed(ValueError("segment shapes do not match the policy"))
            return False
        if int(seg.versions.max()) > self.version:  # acted by weights this train never published
            self.telemetry.count("train/future_version_dropped")
            return False
        self.collector.add(seg)
        self.returns.extend(seg.episode_returns)
        self.telemetry.count("train/segments_received")
        return True

    def take(self) -> list:
        """The next update's items (maybe none: everything pending was too stale)."""
        return self.collector.take(self.version, self.cfg.train.batch_size)

    def update(self, items: list) -> dict[str, float]:
        """Rank 0's update (on the update thread); with several ranks, each learns from a shard, rank 0 the
        first. Makes the next version."""
        if self.dp is not None:
            parts = shards(items, self.collector.size, self.world)
            items = self.dp.send([Command("update", part) for part in parts]).items
        return self.learn(items)

    def learn(self, items: list) -> dict[str, float]:
        """The gradient steps on this rank's items, then ``sync``; a rank without items steps with zero
        gradients. Every rank makes the same collective calls in the same order, items or not."""
        with self.dp.gathered() if self.dp is not None else contextlib.nullcontext():
            batch = self.collector.build(items, self.model).to(self.device) if items else None
        if self.model.obs_norm is not None:  # before the gradient steps, the same statistics on every rank
            sums = self.model.obs_norm.sums(batch.obs if batch is not None else torch.zeros(0, *self.obs_shape))
            self.model.obs_norm.merge(sums if self.dp is None else self.dp.all_sum(sums))
        if batch is None:
            with devices.autocast(self.device, self.cfg.policy.dtype):
                out = {**self.ppo.update(self.empty_batch(), scale=0.0), "batch_size": 0.0}
        else:
            staleness = self.version - batch.versions
            self.staleness_hist += np.bincount(staleness, minlength=len(self.staleness_hist))[:len(self.staleness_hist)]
            with devices.autocast(self.device, self.cfg.policy.dtype):
                out = self.ppo.update(batch, version=self.version)
            out.update(staleness_mean=float(staleness.mean()), staleness_max=float(staleness.max()),
                       batch_size=float(len(batch)))
        self.sync(self.version + 1)
        self.version += 1
        return out

    def sync(self, version: int) -> None:
        """After the update that makes ``version``: the full weights for rank 0 to publish and, when a
        checkpoint is due, the training state (sharded, both are collectives on every rank)."""
        if not self.sharded:
            if self.rank == 0:
                self.arrays = state_arrays(self.model)
            return
        self.arrays = self.dp.full_arrays()  # type: ignore[union-attr]
        every = self.cfg.train.checkpoint_every
        if every and version % every == 0:
            self.train_state = (version, *self.dp.checkpoint_state())  # type: ignore[union-attr]

    def empty_batch(self) -> Batch:
        """Zeros shaped like a batch of ``algo.minibatches`` decisions (for ``scale = 0`` steps)."""
        n = self.cfg.algo.minibatches
        zeros = torch.zeros(n)
        return Batch(obs=torch.zeros(n, *self.obs_shape), actions=torch.zeros(n, *self.action_shape),
                     latents=torch.zeros(n, *self.latent_shape), logprobs=zeros, advantages=zeros, returns=zeros,
                     values=zeros, versions=np.full(n, self.version)).to(self.device)

    def resume(self, floor: int) -> str | None:
        """Carry on from the run's newest readable checkpoint, if any, after version ``floor`` (the newest anyone
        saw before a restart, maybe past the checkpoint) and after every checkpoint on disk (an unreadable one
        was written after its version was published). Returns what happened, or None for a fresh start."""
        if self.rank == 0:  # the writer of checkpoints: what a kill in the middle of a write left goes
            for stale in checkpoint.remove_stale(self.run_dir) + remove_stale_temporaries(self.policy_path):
                log.warning("removed %s, left by an interrupted write", stale)
        restored = checkpoint.restore_latest(self.run_dir, self.model, lambda: self.ppo.optimizer,
                                             {"ppo": self.ppo.generator})  # no checkpoint: no optimizer yet
        if restored is not None:
            self.version = self.saved_version = restored.version
            log.info("resumed from %s (policy v%d)", restored.path, restored.version)
            if restored.newest > restored.version and restored.newest > floor:
                log.warning("checkpoint v%d could not be read, so v%d ... v%d are not reused",
                            restored.newest, restored.version + 1, restored.newest)
                floor = restored.newest
        if floor >= self.version and floor >= 0:
            # also past v0: a train that died in its first update lost that batch, and in a mode without
            # overlap generation waits for v1 before it acts again; the same weights as v1 let the run go on
            log.warning("versions up to v%d were published before the restart; the %s weights continue as v%d",
                        floor, f"v{self.version}" if restored else "initial", floor + 1)
            self.version = floor + 1
        self.arrays = state_arrays(self.model)
        if restored is None and floor < 0:
            return None
        return f"train resumed at policy v{self.version}" + (f" from {restored.path.name}" if restored is not None
                                                              else " with fresh weights")

    def save_checkpoint(self, run_name: str) -> bool:
        """Write the training state (on the update thread, between updates); False if there was nothing new."""
        if self.version == self.saved_version:
            return False
        start = time.time()
        model_state, optimizer = None, self.ppo.optimizer
        if self.sharded:  # what the ranks gathered (sync, and the stop)
            if self.train_state is None or self.train_state[0] != self.version:
                return False
            _, model_state, optimizer = self.train_state
        checkpoint.save(self.run_dir, self.model, optimizer, self.version, {"ppo": self.ppo.generator},
                        {"run": run_name, **self.portable}, model_state=model_state)
        self.saved_version = self.version
        self.telemetry.publish_span("train", "checkpoint", start, time.time())
        self.telemetry.count("train/checkpoints")
        return True

    @property
    def policy_path(self) -> str:
        return os.path.join(self.run_dir, POLICY_FILE)

    def save_policy(self, run_name: str) -> str:
        path = self.policy_path
        weights = {name: torch.from_numpy(a) for name, a in self.arrays.items()}  # full, also when sharded
        save_checkpoint(self.model, path, {"run": run_name, "version": str(self.version), **self.portable},
                        state=weights)
        return path

    def hand_over(self) -> int:
        """Write the segments received and not yet trained on, for the next learner of this run; how many.
        Durably (:func:`ebrl.algos.checkpoint.write_durably`), one checked record per segment
        (:func:`write_records`)."""
        segments = self.collector.segments()
        if segments:
            path = Path(self.run_dir) / HANDOVER_FILE
            checkpoint.write_durably(path, lambda fh: write_records(fh, (encode_message(s) for s in segments)))
        return len(segments)

    def take_over(self, malformed: Callable[[Exception], None]) -> tuple[int, int]:
        """Take over what the learner before handed over, once (the file is removed): (taken, handed over).
        A learner killed while handing over left only the temporary file: its whole records are taken over
        too (each is checked; a torn last one is lost, logged)."""
        path = Path(self.run_dir) / HANDOVER_FILE
        tmp = path.with_name(path.name + ".tmp")
        source = path if path.exists() else tmp if tmp.exists() else None
        if source is None:
            return 0, 0
        payloads, torn = read_records(source)
        if torn:
            log.warning("%s: %s; took the %d whole records before it", source, torn, len(payloads))
        for stale in (path, tmp):  # before anything is trained on: never taken over twice
            stale.unlink(missing_ok=True)
        checkpoint.fsync_dir(path.parent)
        taken = 0
        for payload in payloads:
            try:
                segment = decode_message(TrajectorySegment, payload)
            except MessageError as exc:  # whole, but no segment of this version (another EBRL wrote it)
                malformed(exc)
                continue
            taken += self.accept(segment, malformed)
        self.telemetry.count("train/segments_taken_over", taken)
        return taken, len(payloads)

    def metrics(self) -> dict[str, float]:
        out = {"train/policy_version": float(self.version)}
        if self.rank > 0:
            return out
        out["train/pending_steps"] = float(self.collector.pending_steps)
        if self.returns:
            out["train/episode_return_mean"] = float(np.mean(self.returns))
        for lag, n in enumerate(self.staleness_hist):
            out[f"train/staleness_hist_{lag}"] = float(n)
        return out


def write_records(fh: BinaryIO, payloads: Iterable[bytes]) -> None:
    """The handover file's format: ``HANDOVER_MAGIC``, then one record per payload, each with its length and
    checksum, so that a reader of a file cut short (or with garbage after it) keeps every whole record."""
    fh.write(HANDOVER_MAGIC)
    for payload in payloads:
        fh.write(_RECORD.pack(len(payload), zlib.crc32(payload)))
        fh.write(payload)


def read_records(path: Path) -> tuple[list[bytes], str]:
    """The whole records of a handover file, up to the first torn or garbled one, and what was wrong after them
    ("" for a whole file). A file of the older format (one msgpack list) is read whole or not at all."""
    data = path.read_bytes()
    if not data.startswith(HANDOVER_MAGIC):
        try:
            payloads = msgpack.unpackb(data)
        except (ValueError, msgpack.UnpackException):  # ExtraData and FormatError are ValueErrors
            payloads = None
        if isinstance(payloads, list) and all(isinstance(p, bytes) for p in payloads):
            return payloads, ""
        return [], "not a handover file (no header, not the older format)"
    payloads, at = [], len(HANDOVER_MAGIC)
    while at < len(data):
        if at + _RECORD.size > len(data):
            return payloads, f"record {len(payloads)} is torn (its header is cut short)"
        length, crc = _RECORD.unpack_from(data, at)
        payload = data[at + _RECORD.size:at + _RECORD.size + length]
        if len(payload) < length:
            return payloads, f"record {len(payloads)} is torn ({len(payload)} of {length} bytes)"
        if zlib.crc32(payload) != crc:
            return payloads, f"record {len(payloads)} is garbled (checksum mismatch)"
        payloads.append(payload)
        at += _RECORD.size + length
    return payloads, ""
