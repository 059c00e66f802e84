"""What a learner writes to its run directory, and when.

* the training state (``ebrl.algos.checkpoint``: model, optimizer, generators), every
  ``train.checkpoint_every`` versions and as the run ends: what a restart resumes from;
* the policy file ``RUN_DIR/policy.safetensors`` as the run ends: the newest published weights, loadable on
  their own (``--set policy.checkpoint=RUN_DIR/policy.safetensors``, ``ebrl.load_policy``).

Nothing that is not finite is written: a refused checkpoint leaves the newest good one the one a restart
reads, a refused policy file is not written at all. Only rank 0 writes; with sharded ranks, the state it
writes is the one every rank gathered (``Learner.sync``, and the stop in ``ebrl.algos.ranks``).
"""

from __future__ import annotations

import logging
import os
import time
from typing import TYPE_CHECKING

import torch

from ebrl import durable
from ebrl.algos import checkpoint
from ebrl.policies import save_checkpoint

if TYPE_CHECKING:
    from ebrl.algos.learner import Learner

log = logging.getLogger("ebrl.algos.learner")  # the learner's own log: these are its writes

POLICY_FILE = "policy.safetensors"  # the trained policy, for `--set policy.checkpoint=RUN_DIR/policy.safetensors`


def checkpoint_due(every: int, version: int) -> bool:
    """Whether the update that made ``version`` is followed by a checkpoint (``train.checkpoint_every``; 0:
    only as the run ends)."""
    return bool(every) and version % every == 0


def policy_path(run_dir: str) -> str:
    return os.path.join(run_dir, POLICY_FILE)


def remove_interrupted(run_dir: str) -> list:
    """Remove what a kill in the middle of a write left in ``run_dir`` (a checkpoint's ``*.tmp``, the policy
    file's temporaries); what was removed. Only the writer may call this: a save in progress would go too."""
    return checkpoint.remove_stale(run_dir) + durable.remove_temporaries(policy_path(run_dir))


def save_train_state(learner: Learner, run_name: str) -> bool:
    """Write ``learner``'s training state (on the update thread, between updates); False if there was nothing
    new, or nothing finite (counted: ``train/checkpoints_refused``)."""
    if learner.version == learner.saved_version:
        return False
    start = time.time()
    model_state, optimizer = None, learner.algo.optimizer
    if learner.sharded:  # what the ranks gathered (sync, and the stop)
        if learner.train_state is None or learner.train_state[0] != learner.version:
            return False
        _, model_state, optimizer = learner.train_state
    try:
        checkpoint.save(learner.run_dir, learner.model, optimizer, learner.version, learner.algo.generators(),
                        {"run": run_name, **learner.portable}, model_state=model_state,
                        extra=learner.algo.extra_state())
    except checkpoint.NonFiniteState as exc:  # the newest good checkpoint stays the one a restart reads
        log.error("%s", exc)
        learner.telemetry.count("train/checkpoints_refused")
        return False
    learner.saved_version = learner.version
    learner.telemetry.publish_span("train", "checkpoint", start, time.time())
    learner.telemetry.count("train/checkpoints")
    return True


def save_policy(learner: Learner, run_name: str) -> str | None:
    """Write ``learner``'s newest published weights to ``RUN_DIR/policy.safetensors``; its path, or None where
    they are not finite (then nothing is written, logged)."""
    path = policy_path(learner.run_dir)
    weights = {name: torch.from_numpy(a) for name, a in learner.arrays.items()}  # full, also when sharded
    # the published weights, finite (finite_or_previous); a sharded run's gathered ones are checked here
    if bad := checkpoint.nonfinite(weights):
        log.error("%s not written: values that are not finite (%s)", path, ", ".join(bad[:3]))
        return None
    save_checkpoint(learner.model, path, {"run": run_name, "version": str(learner.version), **learner.portable},
                    state=weights)
    return path


def save_at_end(learner: Learner, run_name: str) -> str | None:
    """As a run ends (or stops to restart): the training state and the policy file, where ``learner`` made a
    version at all; the policy file's path, or None where none was written."""
    if learner.version <= 0:
        return None
    learner.save_checkpoint(run_name)
    return learner.save_policy(run_name)
