"""Policy weights as named arrays: for Weights messages (``state_arrays``/``load_arrays``) and on disk.

A checkpoint is one safetensors file: the model's state dict plus string
metadata, which always holds the policy's ``kind`` (a registered name or a
user's ``"pkg.module:MyPolicy"``), ``chunk``, ``action_dim`` and ``layout``
(``ObsLayout.to_dict`` as JSON); loading checks them against the model before
any tensor, so a checkpoint of another task or policy is refused with a
message that says which of them differs.

Checkpoints written by training (and the eval service's ``best.safetensors``) are
also *portable*: :func:`portable_metadata` adds everything needed to rebuild and
run the policy without the run's config (``ebrl.load_policy``): the whole
``[policy]`` section (its ``options`` as the model holds them), the ``[env]``
section as resolved, the observation shape, the action bounds and the format
version. The observation normaliser's running statistics (``policy.normalize_obs``)
are tensors of the state dict (``obs_norm.mean``, ``obs_norm.var``,
``obs_norm.count``), so they travel too.

Files are written durably and atomically (``ebrl.durable``) and readable as
the umask allows (0644 under the usual 022), never only by their owner. A file
that cannot be read (missing, truncated, not safetensors) is told apart from
one that does not fit the model: :class:`UnreadableCheckpoint`.
"""

from __future__ import annotations

import dataclasses
import json
import os
from typing import Any

import numpy as np
import torch
from safetensors import SafetensorError, safe_open
from safetensors.torch import save_file

from ebrl import durable
from ebrl.policies.base import ChunkPolicy

CHECKED = ("kind", "chunk", "action_dim", "layout")  # reserved metadata keys, written from the model
FORMAT = "ebrl.policy/1"  # metadata["format"] of a portable checkpoint (portable_metadata)
PORTABLE = ("format", "policy", "env", "obs_shape", "action_low", "action_high")  # what portable_metadata adds


class UnreadableCheckpoint(ValueError):
    """A checkpoint file that cannot be read at all (truncated, corrupt, not safetensors), as opposed to one
    that reads but does not fit the model (a plain ValueError)."""


def state_arrays(model: torch.nn.Module) -> dict[str, np.ndarray]:
    """The model's state dict as numpy arrays (what the Weights message carries)."""
    return {name: t.detach().cpu().numpy().copy() for name, t in model.state_dict().items()}


def load_arrays(model: torch.nn.Module, params: dict[str, np.ndarray], source: str = "weights") -> None:
    """Load named arrays into the model; raise ValueError naming every tensor whose name or shape differs."""
    state = model.state_dict()
    if set(params) != set(state):
        raise ValueError(f"{source}: tensor names differ from the model's: missing {sorted(set(state) - set(params))}, "
                         f"unexpected {sorted(set(params) - set(state))}")
    wrong = [f"{name} has shape {tuple(params[name].shape)}, the model's is {tuple(t.shape)}"
             for name, t in state.items() if tuple(params[name].shape) != tuple(t.shape)]
    if wrong:
        raise ValueError(f"{source}: tensor shapes differ from the model's: " + "; ".join(wrong))
    with torch.no_grad():
        for name, tensor in state.items():
            array = params[name]  # torch.from_numpy wants a writable array; a decoded message's views are not
            tensor.copy_(torch.from_numpy(array if array.flags.writeable else np.array(array)))


def policy_metadata(model: ChunkPolicy) -> dict[str, str]:
    return {"kind": model.kind, "chunk": str(model.chunk), "action_dim": str(model.action_dim),
            "layout": json.dumps(model.layout.to_dict())}


def portable_metadata(policy_cfg: Any, env_cfg: Any, info: Any) -> dict[str, str]:
    """What makes a checkpoint loadable without the run's config: ``policy_cfg`` (the ``[policy]`` section;
    its ``checkpoint``, where training started from, is left out), ``env_cfg`` (``[env]`` as resolved) and
    ``info`` (the env's :class:`~ebrl.envs.EnvInfo`: observation shape and action bounds), as JSON strings."""
    from ebrl import __version__

    policy = dataclasses.asdict(policy_cfg)
    policy["checkpoint"] = ""
    return {"format": FORMAT, "ebrl_version": __version__, "policy": json.dumps(policy),
            "env": json.dumps(dataclasses.asdict(env_cfg)), "obs_shape": json.dumps(list(info.obs_shape)),
            "action_low": json.dumps([float(x) for x in info.action_space.low]),
            "action_high": json.dumps([float(x) for x in info.action_space.high])}


def read_metadata(path: str) -> dict[str, str]:
    """The string metadata of the safetensors file at ``path`` (no tensor is read)."""
    if not os.path.isfile(path):
        raise FileNotFoundError(f"policy checkpoint {path}: no such file")
    try:
        with safe_open(path, framework="pt") as fh:
            return dict(fh.metadata() or {})
    except (SafetensorError, OSError) as exc:
        raise UnreadableCheckpoint(f"policy checkpoint {path}: not a readable safetensors file ({exc})") from None


def save_checkpoint(model: ChunkPolicy, path: str, metadata: dict[str, str],
                    state: dict[str, torch.Tensor] | None = None) -> None:
    """Write the weights (``state``, default the model's own) and ``metadata`` (plus the reserved keys
    ``CHECKED``) atomically to ``path``. Portable metadata's ``[policy]`` section gets the model's own kind and
    options (:func:`rebuilt_by`)."""
    tensors = {name: t.detach().cpu().contiguous() for name, t in (state or model.state_dict()).items()}
    if "policy" in metadata:
        metadata = {**metadata, "policy": rebuilt_by(model, metadata["policy"])}
    os.makedirs(os.path.dirname(os.path.abspath(path)), exist_ok=True)
    with durable.writing(path) as tmp:  # as the umask allows: the group (a collaborator, a server) may read it
        save_file(tensors, str(tmp), metadata={**metadata, **policy_metadata(model)})


def rebuilt_by(model: ChunkPolicy, policy_json: str) -> str:
    """The ``[policy]`` section (JSON) with what rebuilds ``model`` from the checkpoint alone: its kind (a user's
    ``"pkg.module:MyPolicy"``, imported again by ``ebrl.load_policy``) and its ``options`` (the config's, or what
    the kind put in their place: a pretrained model's architecture rather than the directory it came from)."""
    section = json.loads(policy_json)
    section["kind"] = model.kind
    section["options"] = dict(model.options or {})
    return json.dumps(section)


def read_checkpoint(model: ChunkPolicy, path: str) -> tuple[dict[str, np.ndarray], dict[str, str]]:
    """The weights at ``path`` (every tensor read, none loaded yet) and the file's metadata, after checking kind,
    chunk, action_dim and layout against ``model``. FileNotFoundError for a missing file, UnreadableCheckpoint
    for one that cannot be read, ValueError for one that does not match."""
    if not os.path.isfile(path):
        raise FileNotFoundError(f"policy checkpoint {path}: no such file")
    try:
        with safe_open(path, framework="pt") as fh:
            metadata = fh.metadata() or {}
            expected = policy_metadata(model)
            for key in CHECKED:
                if metadata.get(key) != expected[key]:
                    raise ValueError(f"policy checkpoint {path}: {key} is {metadata.get(key, 'not recorded')!r}, "
                                     f"the model's is {expected[key]!r}")
            arrays = {name: fh.get_tensor(name).numpy() for name in fh.keys()}
    except (SafetensorError, OSError) as exc:
        raise UnreadableCheckpoint(f"policy checkpoint {path}: not a readable safetensors file ({exc})") from None
    return arrays, metadata


def load_checkpoint(model: ChunkPolicy, path: str) -> dict[str, str]:
    """Load the weights at ``path`` into ``model`` after checking kind, chunk, action_dim and layout; return
    the file's metadata. FileNotFoundError for a missing file, ValueError for anything that does not match
    (UnreadableCheckpoint, a ValueError, for a file that cannot be read)."""
    arrays, metadata = read_checkpoint(model, path)
    load_arrays(model, arrays, source=f"policy checkpoint {path}")
    return metadata
