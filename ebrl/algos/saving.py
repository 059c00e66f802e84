"""What a learner writes to its run directory, and when.

* the training state (``ebrl.algos.checkpoint``: model, optimizer, generators), every
  ``train.checkpoint_every`` versions and as the run ends: what a restart resumes from;
* the policy file ``RUN_DIR/policy.safetensors`` as the run ends: the newest published weights, loadable on
  their own (``--set policy.checkpoint=RUN_DIR/policy.safetensors``, ``ebrl.load_policy``).

Nothing that is not finite is written: a refused checkpoint leaves the newest good one the one a restart
reads, a refused policy file is not written at all. Only rank 0 writes; with sharded ranks, the state it
writes is the one every rank gathered (``Learner.sync``, and the stop in ``ebrl.algos.ranks``).

The learner decides when and hands over what to write (:meth:`ebrl.algos.learner.Learner.save_checkpoint`,
``save_policy``, ``save_at_end``); this module only writes it, and knows nothing of the learner.
"""

from __future__ import annotations

import logging
import os
import time
from typing import TYPE_CHECKING, Any

import numpy as np
import torch

from ebrl import durable
from ebrl.algos import checkpoint
from ebrl.policies import save_checkpoint

if TYPE_CHECKING:
    from ebrl.meter import Telemetry

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


def save_train_state(run_dir: str, model: torch.nn.Module, optimizer: Any, version: int, metadata: dict[str, str],
                     telemetry: Telemetry, generators: dict[str, Any], extra: dict[str, torch.Tensor],
                     model_state: dict[str, torch.Tensor] | None = None) -> bool:
    """Write the training state of ``version`` to ``run_dir`` (the learner calls it on the update thread, between
    updates, when it has a new version: ``Learner.save_checkpoint``); False where it is not finite (then nothing
    is written, counted: ``train/checkpoints_refused``). ``model_state``: the model's state gathered from sharded
    ranks, written instead of ``model``'s own."""
    start = time.time()
    try:
        checkpoint.save(run_dir, model, optimizer, version, generators, metadata, model_state=model_state,
                        extra=extra)
    except checkpoint.NonFiniteState as exc:  # the newest good checkpoint stays the one a restart reads
        log.error("%s", exc)
        telemetry.count("train/checkpoints_refused")
        return False
    telemetry.publish_span("train", "checkpoint", start, time.time())
    telemetry.count("train/checkpoints")
    return True


def save_policy(run_dir: str, model: torch.nn.Module, arrays: dict[str, np.ndarray],
                metadata: dict[str, str]) -> str | None:
    """Write the published weights ``arrays`` (full, also when sharded) as ``model``'s policy file
    ``RUN_DIR/policy.safetensors``; its path, or None where they are not finite (then nothing is written,
    logged)."""
    path = policy_path(run_dir)
    weights = {name: torch.from_numpy(a) for name, a in arrays.items()}
    # the published weights, finite (finite_or_previous); a sharded run's gathered ones are checked here
    if bad := checkpoint.nonfinite(weights):
        log.error("%s not written: values that are not finite (%s)", path, ", ".join(bad[:3]))
        return None
    save_checkpoint(model, path, metadata, state=weights)
    return path
