"""Policy weights as named arrays: for Weights messages (``state_arrays``/``load_arrays``) and on disk.

A checkpoint is one safetensors file: the model's state dict plus string
metadata, which always holds the policy's ``kind``, ``chunk``, ``action_dim``
and ``layout`` (``ObsLayout.to_dict`` as JSON); loading checks them against the
model before any tensor, so a checkpoint of another task or policy is refused
with a message that says which of them differs.
"""

from __future__ import annotations

import json
import os
import tempfile

import numpy as np
import torch
from safetensors import SafetensorError, safe_open
from safetensors.torch import save_file

from ebrl.policies.base import ChunkPolicy

CHECKED = ("kind", "chunk", "action_dim", "layout")  # reserved metadata keys, written from the model


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


def save_checkpoint(model: ChunkPolicy, path: str, metadata: dict[str, str],
                    state: dict[str, torch.Tensor] | None = None) -> None:
    """Write the weights (``state``, default the model's own) and ``metadata`` (plus the reserved keys
    ``CHECKED``) atomically to ``path``."""
    tensors = {name: t.detach().cpu().contiguous() for name, t in (state or model.state_dict()).items()}
    directory = os.path.dirname(os.path.abspath(path))
    os.makedirs(directory, exist_ok=True)
    fd, tmp = tempfile.mkstemp(prefix=".checkpoint-", suffix=".tmp", dir=directory)
    os.close(fd)
    try:
        save_file(tensors, tmp, metadata={**metadata, **policy_metadata(model)})
        os.replace(tmp, path)
    except BaseException:
        os.unlink(tmp)
        raise


def load_checkpoint(model: ChunkPolicy, path: str) -> dict[str, str]:
    """Load the weights at ``path`` into ``model`` after checking kind, chunk, action_dim and layout; return
    the file's metadata. FileNotFoundError for a missing file, ValueError for anything that does not match."""
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
    except SafetensorError as exc:
        raise ValueError(f"policy checkpoint {path}: not a readable safetensors file ({exc})") from None
    load_arrays(model, arrays, source=f"policy checkpoint {path}")
    return metadata
