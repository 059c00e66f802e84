"""The learner of one training rank (Sample Factory's ``Learner``): segments in, updates, versioned weights.

It holds the policy, the algorithm (``algo.name``: ``ebrl.algos.algorithm``) and its bounded collector, and the
rules that keep versions honest, the same for every algorithm:

* a segment is taken only if its shapes match the policy and it was acted by a version this learner
  published (``versions <= version``); a bad one is dropped, counted;
* versions never go back or repeat: a restart resumes from the run's latest checkpoint and, when the
  launcher says a newer version was published before (``procenv.version_floor``), continues after it;
* a learner stopped to start again (a new GPU share) hands the segments it had not trained on over to
  the next one (``ebrl.algos.handover``), which takes them over once;
* nothing that is not finite is learned from, published, saved or resumed from (the algorithm skips a bad
  gradient step, :meth:`Learner.finite_or_previous` undoes an update that made non-finite weights,
  ``ebrl.algos.saving`` refuses a checkpoint or policy file that is not finite).

No bus and no event loop here: the train service (``ebrl/services/train.py``) drives it through
``ebrl.algos.cycle``, and with several ranks the choreography of ``ebrl.algos.parallel`` decides who learns
from what.
"""

from __future__ import annotations

import logging
from typing import Any, Callable

import numpy as np
import torch

from ebrl import devices
from ebrl.algos import checkpoint, handover, saving
from ebrl.algos.algorithm import algorithm_class
from ebrl.algos.intake import Intake
from ebrl.algos.returns import EpisodeLedger, RewardBound
from ebrl.algos.parallel import Command, DataParallel, shards
from ebrl.messages import SegmentBatch, TrajectorySegment
from ebrl.policies import load_arrays, make_policy, state_arrays
from ebrl.policies.checkpoint import portable_metadata
from ebrl.meter import Telemetry

log = logging.getLogger(__name__)

MAX_LAG_SHOWN = 16  # staleness histogram bins (train/staleness_hist_<lag>): an off-policy run's lags are unbounded


class Learner:
    """One rank's policy, optimiser and pending data; ``version`` is the newest policy version it made."""

    def __init__(self, cfg: Any, info: Any, max_staleness: int, telemetry: Telemetry, run_dir: str,
                 rank: int = 0, world: int = 1):
        self.cfg, self.telemetry, self.run_dir, self.rank, self.world = cfg, telemetry, run_dir, rank, world
        torch.manual_seed(cfg.run.seed)
        self.device = devices.rank_device(cfg.train.device, "train.device", rank)
        self.obs_shape = info.obs_shape
        self.action_shape = (cfg.policy.chunk, info.action_dim)
        # before the optimizer
        self.model = make_policy(cfg.policy, info.layout, info.action_dim, info.bounds).to(self.device)
        self.portable = portable_metadata(cfg.policy, cfg.env, info)  # every policy file: loadable on its own
        self.latent_shape = tuple(self.model.latent_shape)
        self.algo = algorithm_class(cfg.algo.name)(self.model, cfg, info, telemetry, self.device)
        self.version = self.saved_version = 0
        self.dp: DataParallel | None = None
        self.collector = self.algo.collector(cfg.train.max_pending, max_staleness, telemetry.count)
        # every env's episodes as training received them: the returns it computed, the ones the run ends on
        self.intake = Intake(cfg.env.max_abs_reward, EpisodeLedger(RewardBound(cfg.env.reward_bound,
                                                                                 info.reward_range)), telemetry)
        # decisions per lag (the last bin: that lag or more)
        self.staleness_hist = np.zeros(min(max_staleness, MAX_LAG_SHOWN) + 1, dtype=np.int64)
        self.arrays: dict[str, np.ndarray] = {}  # the full weights rank 0 publishes
        self.train_state: tuple[int, dict, dict] | None = None  # sharded: (version, model, optimizer) gathered

    def join(self) -> None:
        """With several ranks: join the training group (blocks until every rank joined; every rank then
        holds rank 0's weights)."""
        self.dp = DataParallel(self.model, self.algo.optimizer, self.rank, self.world,
                               shard=self.cfg.train.parallel == "fsdp", device=self.device, wire=self.collector)
        self.algo.join(self.dp)

    @property
    def sharded(self) -> bool:
        return self.dp is not None and self.dp.shard

    @property
    def ready(self) -> bool:
        return self.collector.ready_steps >= self.cfg.train.batch_size

    def accept(self, item: TrajectorySegment | SegmentBatch, malformed: Callable[[Exception], None],
               handed: bool = False) -> int:
        """Check a segment, or a vectorized group's packed segments, against this policy and add them to the
        collector; returns how many were taken (the others dropped, counted: ``ebrl.algos.intake``). Their own
        consistency (lengths, finite values) was checked as they were decoded. ``handed``: handed over by the
        learner before (its segments and env steps were counted there, so not again)."""
        if item.obs.shape[1:] != self.obs_shape or item.actions.shape[1:] != self.action_shape \
                or item.latents.shape[1:] != self.latent_shape:
            malformed(ValueError("segment shapes do not match the policy"))
            return 0
        taken = self.intake.take(item, self.version, handed)
        for seg in taken:
            self.collector.add(seg)
        return len(taken)

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
        """The algorithm's update on this rank's items, then ``sync``; a rank without items takes part too
        (every rank makes the same collective calls in the same order, items or not)."""
        learned = self.algo.learn(items, self.version, self.collector)
        if learned.versions is not None:
            lags = np.minimum(self.version - learned.versions, len(self.staleness_hist) - 1)
            self.staleness_hist += np.bincount(lags, minlength=len(self.staleness_hist))
        out = learned.stats
        count_skipped(out, self.telemetry, self.version + 1)
        self.sync(self.version + 1)
        if self.dp is not None:  # every rank, every update: a collective
            self.telemetry.count("train/ranks_checked")
            if not self.dp.weights_agree():
                self.telemetry.count("train/ranks_diverged")
                log.error("after the update to v%d the training ranks hold different weights", self.version + 1)
        self.version += 1
        return out

    def sync(self, version: int) -> None:
        """After the update that makes ``version``: the full weights for rank 0 to publish and, when a
        checkpoint is due, the training state (sharded, both are collectives on every rank)."""
        if not self.sharded:
            if self.rank == 0:
                self.arrays = self.finite_or_previous(state_arrays(self.model))
            return
        self.arrays = self.dp.full_arrays()  # type: ignore[union-attr]
        if saving.checkpoint_due(self.cfg.train.checkpoint_every, version):
            self.train_state = (version, *self.dp.checkpoint_state())  # type: ignore[union-attr]

    def finite_or_previous(self, arrays: dict[str, np.ndarray]) -> dict[str, np.ndarray]:
        """``arrays``, or where a value in them is not finite the last published weights, loaded back into the
        model, the optimizer's moments cleared (counted: ``train/weights_refused``)."""
        if not (bad := checkpoint.nonfinite({name: torch.from_numpy(a) for name, a in arrays.items()})):
            return arrays
        self.telemetry.count("train/weights_refused")
        log.error("the update to v%d made non-finite weights (%s): v%d's kept", self.version + 1, bad[0], self.version)
        if self.arrays:
            load_arrays(self.model, self.arrays)
        self.algo.reset_moments()  # the moments that led there
        return self.arrays or arrays

    def resume(self, floor: int) -> str | None:
        """Carry on from the run's newest readable checkpoint, if any, after version ``floor`` (the newest anyone
        saw before a restart, maybe past the checkpoint) and after every checkpoint on disk (an unreadable one
        was written after its version was published). Returns what happened, or None for a fresh start."""
        if self.rank == 0:  # the writer of checkpoints: what a kill in the middle of a write left goes
            for stale in saving.remove_interrupted(self.run_dir):
                log.warning("removed %s, left by an interrupted write", stale)
        restored = checkpoint.restore_latest(self.run_dir, self.model, lambda: self.algo.optimizer,
                                             self.algo.generators(), self.algo.load_extra_state)
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
        """Write the training state (on the update thread, between updates: :func:`ebrl.algos.saving.save_train_state`);
        False if there was nothing new, or nothing finite. Sharded, the state the ranks gathered (sync, the stop)."""
        if self.version == self.saved_version:
            return False
        model_state, optimizer = None, self.algo.optimizer
        if self.sharded:
            if self.train_state is None or self.train_state[0] != self.version:
                return False
            _, model_state, optimizer = self.train_state
        if not saving.save_train_state(self.run_dir, self.model, optimizer, self.version,
                                       {"run": run_name, **self.portable}, self.telemetry, self.algo.generators(),
                                       self.algo.extra_state(), model_state=model_state):
            return False
        self.saved_version = self.version
        return True

    def save_policy(self, run_name: str) -> str | None:
        """Write the newest published weights to ``RUN_DIR/policy.safetensors``; its path, or None where they are
        not finite (:func:`ebrl.algos.saving.save_policy`)."""
        return saving.save_policy(self.run_dir, self.model, self.arrays,
                                  {"run": run_name, "version": str(self.version), **self.portable})

    def save_at_end(self, run_name: str) -> str | None:
        """As a run ends (or stops to restart): the training state and the policy file, where this learner made a
        version at all; the policy file's path, or None where none was written."""
        if self.version <= 0:
            return None
        self.save_checkpoint(run_name)
        return self.save_policy(run_name)

    def hand_over(self) -> int:
        """The segments not yet trained on, written for the next learner (:func:`ebrl.algos.handover.hand_over`)."""
        return handover.hand_over(self.run_dir, self.collector.segments())

    def take_over(self, malformed: Callable[[Exception], None]) -> tuple[int, int]:
        """(taken, handed over) of what the learner before left (:func:`ebrl.algos.handover.take_over`)."""
        taken, handed = handover.take_over(self.run_dir, lambda segment: self.accept(segment, malformed, handed=True),
                                          malformed)
        self.telemetry.count("train/segments_taken_over", taken)
        return taken, handed

    def metrics(self) -> dict[str, float]:
        out = {"train/policy_version": float(self.version), "train/dtype": devices.dtype_bits(self.cfg.policy.dtype)}
        if self.rank > 0:
            return out
        # batch_ready: a full batch waits, which the stall watch reads (ebrl.stall)
        out.update({"train/pending_steps": float(self.collector.pending_steps), "train/batch_ready": float(self.ready)})
        out.update(self.intake.metrics())  # the returns training computed (ebrl.algos.returns), its intake
        out.update(self.algo.metrics())  # the algorithm's own (a replay's size and rates)
        for lag, n in enumerate(self.staleness_hist):
            out[f"train/staleness_hist_{lag}"] = float(n)
        return out


def count_skipped(out: dict[str, float], telemetry: Telemetry, version: int) -> None:
    """Count the gradient steps an update skipped and the decisions it dropped (``train/updates_skipped``,
    ``train/decisions_dropped``), taken out of ``out``: totals, not the update's own numbers."""
    skipped, dropped = out.pop("steps_skipped", 0.0), out.pop("decisions_dropped", 0.0)
    if skipped:
        telemetry.count("train/updates_skipped", skipped)
        telemetry.count("train/decisions_dropped", dropped)
        log.warning("v%d: %d gradient step(s) skipped, their loss or gradient not finite; %d decisions dropped",
                    version, skipped, dropped)
