"""Training checkpoints: everything a restarted or resumed train service needs to carry on.

A checkpoint is a directory ``RUN_DIR/checkpoints/v<version>/`` holding

- ``policy.safetensors``: the policy (``ebrl.policies.save_checkpoint``: weights plus the policy's kind,
  chunk, action size and observation layout, checked on load);
- ``train.safetensors``: the optimizer's tensors (``opt.<param index>.<name>``) and the random
  generators' states (``rng.torch``, ``rng.ppo``);
- ``state.json``: the policy version, the optimizer's hyper-parameters (param groups) and when it was
  written.

It is written into ``v<version>.tmp/`` and renamed into place, then ``latest`` (a one-line file naming the
directory) is replaced atomically, so a crash at any moment leaves the previous checkpoint intact and
``latest`` always names a complete one. The newest ``KEEP`` checkpoints are kept.
"""

from __future__ import annotations

import json
import os
import shutil
import time
from dataclasses import dataclass
from pathlib import Path
from typing import Any

import torch
from safetensors.torch import load_file, save_file

from ebrl.policies import load_checkpoint, save_checkpoint

DIRNAME = "checkpoints"
KEEP = 2


@dataclass
class Restored:
    version: int
    path: Path


def checkpoint_dir(run_dir: str | Path) -> Path:
    return Path(run_dir) / DIRNAME


def latest(run_dir: str | Path) -> Path | None:
    """The newest complete checkpoint of a run, or None."""
    root = checkpoint_dir(run_dir)
    try:
        name = (root / "latest").read_text().strip()
    except FileNotFoundError:
        return None
    path = root / name
    return path if (path / "state.json").is_file() else None


def save(run_dir: str | Path, model: torch.nn.Module, optimizer: torch.optim.Optimizer | dict, version: int,
         generators: dict[str, torch.Generator], metadata: dict[str, str] | None = None,
         model_state: dict[str, torch.Tensor] | None = None) -> Path:
    """Write a checkpoint of ``version`` atomically; return its directory. ``optimizer`` may be its state dict
    and ``model_state`` the model's, gathered elsewhere (sharded training: ``ebrl.algos.parallel``)."""
    root = checkpoint_dir(run_dir)
    name = f"v{version:08d}"
    tmp, final = root / f"{name}.tmp", root / name
    shutil.rmtree(tmp, ignore_errors=True)
    tmp.mkdir(parents=True)
    save_checkpoint(model, str(tmp / "policy.safetensors"), {**(metadata or {}), "version": str(version)},
                    state=model_state)
    state = optimizer if isinstance(optimizer, dict) else optimizer.state_dict()
    tensors = {f"opt.{index}.{key}": value.detach().cpu().contiguous()
               for index, slots in state["state"].items() for key, value in slots.items()
               if isinstance(value, torch.Tensor)}
    tensors.update({f"rng.{key}": gen.get_state() for key, gen in generators.items()})
    tensors["rng.torch"] = torch.get_rng_state()
    save_file(tensors, str(tmp / "train.safetensors"))
    (tmp / "state.json").write_text(json.dumps({"version": version, "time": time.time(),
                                                "param_groups": state["param_groups"]}, indent=1) + "\n")
    _fsync_dir(tmp)
    shutil.rmtree(final, ignore_errors=True)
    os.replace(tmp, final)
    pointer = root / "latest.tmp"
    pointer.write_text(name + "\n")
    os.replace(pointer, root / "latest")
    _fsync_dir(root)
    for old in sorted(p for p in root.glob("v*") if p.is_dir() and not p.name.endswith(".tmp"))[:-KEEP]:
        shutil.rmtree(old, ignore_errors=True)
    return final


def restore(path: Path, model: torch.nn.Module, optimizer: torch.optim.Optimizer,
            generators: dict[str, torch.Generator]) -> Restored:
    """Load a checkpoint directory into the model, optimizer and generators; raise ValueError when it does
    not fit them (another policy, another optimizer)."""
    meta = json.loads((path / "state.json").read_text())
    load_checkpoint(model, str(path / "policy.safetensors"))
    tensors = load_file(str(path / "train.safetensors"))
    slots: dict[int, dict[str, Any]] = {}
    for key, value in tensors.items():
        if key.startswith("opt."):
            _, index, name = key.split(".", 2)
            slots.setdefault(int(index), {})[name] = value
    try:
        optimizer.load_state_dict({"state": slots, "param_groups": meta["param_groups"]})
    except (ValueError, KeyError) as exc:
        raise ValueError(f"checkpoint {path}: optimizer state does not fit this model: {exc}") from None
    for key, gen in generators.items():
        if f"rng.{key}" in tensors:
            gen.set_state(tensors[f"rng.{key}"])
    torch.set_rng_state(tensors["rng.torch"])
    return Restored(version=int(meta["version"]), path=path)


def _fsync_dir(path: Path) -> None:
    fd = os.open(path, os.O_RDONLY)
    try:
        os.fsync(fd)
    finally:
        os.close(fd)
