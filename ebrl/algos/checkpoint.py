"""Training checkpoints: everything a restarted or resumed train service needs to carry on.

A checkpoint is a directory ``RUN_DIR/checkpoints/v<version>/`` holding

- ``policy.safetensors``: the policy (``ebrl.policies.save_checkpoint``: weights plus the policy's kind,
  chunk, action size and observation layout, checked on load);
- ``train.safetensors``: the optimizer's tensors (``opt.<param index>.<name>``) and the random
  generators' states (``rng.torch``, ``rng.ppo``);
- ``state.json``: the policy version, the optimizer's hyper-parameters (param groups) and when it was
  written.

Durability (``ebrl.durable``): every file is written into ``v<version>.tmp/``, which goes into place whole
(:func:`ebrl.durable.replace_dir`: its files and itself fsynced, renamed, the parent fsynced); only then is
``latest`` (a one-line file naming the directory) replaced, durably too. A checkpoint counts once
``latest`` names it, so a crash (kill -9, power loss) at any moment leaves the previous one intact. The new
checkpoint and the newest ``KEEP - 1`` whole ones before it are kept; an older one (or one that is not whole)
is renamed to ``*.tmp`` before it is deleted, so a crash while deleting never leaves half a checkpoint under a
``v*`` name. What a crash left (``*.tmp``) is removed at the next save and when training starts
(:func:`remove_stale`).

Restoring (:func:`restore_latest`) tries the checkpoint ``latest`` names, then every other ``v*`` directory,
newest first: one that cannot be read (a missing or truncated file, a bad ``state.json``) is skipped, logged
with the reason; a dangling or garbage ``latest`` is ignored the same way. One that reads but does not fit the
model (another policy or optimizer) is an error, not skipped: every checkpoint of the run would be the same.
"""

from __future__ import annotations

import json
import logging
import os
import re
import shutil
import time
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any, Callable

import torch
from safetensors import SafetensorError, safe_open
from safetensors.torch import load_file, save_file

from ebrl import durable
from ebrl.policies import save_checkpoint
from ebrl.policies.checkpoint import UnreadableCheckpoint, load_arrays, read_checkpoint

log = logging.getLogger(__name__)

DIRNAME = "checkpoints"
KEEP = 2
POINTER = "latest"
_NAME = re.compile(r"v(\d+)")  # a checkpoint directory's name: v<version>, 8 digits


@dataclass
class Restored:
    version: int
    path: Path
    skipped: list[tuple[Path, str]] = field(default_factory=list)  # newer checkpoints that could not be read, why
    newest: int = -1  # the highest version any checkpoint directory names, read or not (versions never repeat)


class Unreadable(Exception):
    """A checkpoint directory that cannot be read (the message says why); restore falls back past it."""


def checkpoint_dir(run_dir: str | Path) -> Path:
    return Path(run_dir) / DIRNAME


def version_of(path: Path) -> int | None:
    """The version a checkpoint directory's name says (``v00000012`` -> 12), None for any other name."""
    match = _NAME.fullmatch(path.name)
    return int(match.group(1)) if match else None


def candidates(run_dir: str | Path) -> list[Path]:
    """The checkpoint directories of a run in the order a restore tries them: the one ``latest`` names, then
    every other ``v*`` directory, newest first (a dangling or garbage ``latest`` names none)."""
    root = checkpoint_dir(run_dir)
    found = sorted((p for p in _listdir(root) if p.is_dir() and version_of(p) is not None),
                   key=lambda p: version_of(p), reverse=True)  # type: ignore[arg-type, return-value]
    try:
        named = root / (root / POINTER).read_text().strip()
    except (OSError, UnicodeDecodeError):
        return found
    if named not in found:
        return found
    return [named] + [p for p in found if p != named]


def latest(run_dir: str | Path) -> Path | None:
    """The newest complete checkpoint of a run (``latest``, or if that names none that looks complete, the newest
    ``v*`` directory that does), or None. Complete: ``state.json`` reads and both safetensors files open (their
    headers; :func:`restore_latest` reads every tensor and falls back further if one cannot be read)."""
    return next((path for path in candidates(run_dir) if looks_complete(path)), None)


def looks_complete(path: Path) -> bool:
    """Whether a checkpoint directory's ``state.json`` reads and its safetensors files are whole (their headers
    read and the file sizes they imply match; no tensor is read)."""
    try:
        _read_state(path)
        for name in ("policy.safetensors", "train.safetensors"):
            with safe_open(str(path / name), framework="pt"):
                pass
    except (Unreadable, SafetensorError, OSError):
        return False
    return True


def remove_stale(run_dir: str | Path) -> list[Path]:
    """Remove what an interrupted save left in the run's checkpoint directory (``*.tmp``); returns it.
    Only the process that writes checkpoints may call this (it would remove a save in progress)."""
    removed = []
    for stale in _listdir(checkpoint_dir(run_dir)):
        if stale.name.endswith(durable.SUFFIX):  # a v*.tmp directory, or a file's temporary (ebrl.durable)
            if stale.is_dir() and not stale.is_symlink():
                shutil.rmtree(stale, ignore_errors=True)
            else:
                stale.unlink(missing_ok=True)
            removed.append(stale)
    return removed


def save(run_dir: str | Path, model: torch.nn.Module, optimizer: Any, version: int,
         generators: dict[str, torch.Generator], metadata: dict[str, str] | None = None,
         model_state: dict[str, torch.Tensor] | None = None, extra: dict[str, torch.Tensor] | None = None) -> Path:
    """Write a checkpoint of ``version`` durably and atomically; return its directory. ``optimizer`` may be its
    state dict and ``model_state`` the model's, gathered elsewhere (sharded training: ``ebrl.algos.parallel``).
    ``extra``: the algorithm's tensors beyond the policy and optimizer (``Algorithm.extra_state``: critics,
    targets), written as ``algo.<name>``."""
    root = checkpoint_dir(run_dir)
    root.mkdir(parents=True, exist_ok=True)
    for stale in remove_stale(run_dir):
        log.warning("removed %s, left by an interrupted checkpoint write", stale)
    name = f"v{version:08d}"
    tmp, final = root / f"{name}.tmp", root / name
    tmp.mkdir(exist_ok=True)  # a leftover remove_stale could not delete is written over
    save_checkpoint(model, str(tmp / "policy.safetensors"), {**(metadata or {}), "version": str(version)},
                    state=model_state)
    state = optimizer if isinstance(optimizer, dict) else optimizer.state_dict()
    tensors = {f"opt.{index}.{key}": value.detach().cpu().contiguous()
               for index, slots in state["state"].items() for key, value in slots.items()
               if isinstance(value, torch.Tensor)}
    tensors.update({f"algo.{key}": value.detach().cpu().contiguous() for key, value in (extra or {}).items()})
    bad = nonfinite({**(model_state if model_state is not None else model.state_dict()), **tensors})
    if bad:
        shutil.rmtree(tmp, ignore_errors=True)
        raise NonFiniteState(f"checkpoint v{version} not written: values that are not finite ({', '.join(bad[:3])})")
    tensors.update({f"rng.{key}": gen.get_state() for key, gen in generators.items()})
    tensors["rng.torch"] = torch.get_rng_state()
    save_file(tensors, str(tmp / "train.safetensors"))
    text = json.dumps({"version": version, "time": time.time(), "param_groups": state["param_groups"]}, indent=1)
    (tmp / "state.json").write_text(text + "\n")
    durable.replace_dir(tmp, final)  # the same version again: the old one goes first (a crash then falls back)
    durable.write_text(root / POINTER, f"{name}\n")  # once the directory is there
    others = [p for p in candidates(run_dir) if p != final]
    kept = [p for p in others if looks_complete(p)][:KEEP - 1]  # an unreadable one is not worth keeping
    for old in others:
        if old in kept or version_of(old) > version:  # type: ignore[operator]
            continue
        doomed = old.with_name(old.name + ".old.tmp")  # out of the v* names at once, then deleted
        os.replace(old, doomed)
        shutil.rmtree(doomed, ignore_errors=True)
    return final


class NonFiniteState(ValueError):
    """Training state with a value that is not finite: never written, never resumed from."""


def restore_latest(run_dir: str | Path, model: torch.nn.Module,
                   optimizer: torch.optim.Optimizer | Callable[[], torch.optim.Optimizer],
                   generators: dict[str, torch.Generator],
                   extra: Callable[[dict[str, torch.Tensor]], None] | None = None) -> Restored | None:
    """Load the newest readable checkpoint of a run (:func:`candidates`' order) into the model, optimizer and
    generators, skipping (and logging) each that cannot be read; None when there is none to read. Raises
    ValueError when a checkpoint reads but does not fit the model or optimizer. ``optimizer`` may be a function
    that makes it, called only once a checkpoint was read (a new run makes its optimizer later: ``PPO``).
    ``extra`` takes the algorithm's own tensors (``algo.<name>``; ``Algorithm.load_extra_state``)."""
    paths = candidates(run_dir)
    newest = max((version_of(p) for p in paths), default=-1)  # type: ignore[type-var]
    skipped: list[tuple[Path, str]] = []
    for path in paths:
        try:
            loaded = _read(path, model)
        except Unreadable as exc:
            log.warning("checkpoint %s skipped: %s", path, exc)
            skipped.append((path, str(exc)))
            continue
        if skipped:
            log.warning("restoring %s instead (%d newer checkpoint%s unreadable)", path.name, len(skipped),
                        "s" if len(skipped) > 1 else "")
        restored = _apply(path, loaded, model, optimizer() if callable(optimizer) else optimizer, generators, extra)
        restored.skipped, restored.newest = skipped, max(newest, restored.version)
        return restored
    if skipped:
        log.warning("no readable checkpoint in %s (%d skipped)", checkpoint_dir(run_dir), len(skipped))
    return None


def restore(path: Path, model: torch.nn.Module, optimizer: torch.optim.Optimizer,
            generators: dict[str, torch.Generator]) -> Restored:
    """Load one checkpoint directory into the model, optimizer and generators; raise ValueError when it cannot
    be read or does not fit them (another policy, another optimizer). Nothing is loaded unless all of it reads."""
    try:
        loaded = _read(path, model)
    except Unreadable as exc:
        raise ValueError(f"checkpoint {path}: {exc}") from None
    return _apply(path, loaded, model, optimizer, generators)


def _read(path: Path, model: torch.nn.Module) -> tuple[dict, dict, dict]:
    """Everything in a checkpoint directory, read and checked, nothing applied: (state, weights, tensors).
    Raises Unreadable (missing or unreadable files) or ValueError (a policy that does not fit ``model``)."""
    state = _read_state(path)
    try:
        arrays, _ = read_checkpoint(model, str(path / "policy.safetensors"))
    except (FileNotFoundError, UnreadableCheckpoint) as exc:
        raise Unreadable(str(exc)) from None
    try:
        tensors = load_file(str(path / "train.safetensors"))
    except (SafetensorError, OSError) as exc:
        raise Unreadable(f"train.safetensors: {exc}") from None
    rng = tensors.get("rng.torch")
    if rng is None or rng.dtype != torch.uint8:
        raise Unreadable("train.safetensors: no random state (rng.torch)")
    bad = nonfinite({**{f"policy.{k}": torch.as_tensor(v) for k, v in arrays.items()}, **tensors})
    if bad:  # never resumed from (nothing writes one now: save refuses; an older EBRL's or a forged one)
        raise Unreadable(f"values that are not finite ({', '.join(bad[:3])})")
    return state, arrays, tensors


def nonfinite(tensors: dict[str, torch.Tensor]) -> list[str]:
    """The names of the floating-point tensors that hold a value that is not finite."""
    return [name for name, t in tensors.items() if t.is_floating_point() and not bool(torch.isfinite(t).all())]


def _read_state(path: Path) -> dict[str, Any]:
    try:
        state = json.loads((path / "state.json").read_text())
        if not isinstance(state.get("version"), int) or not isinstance(state.get("param_groups"), list):
            raise ValueError("no version or param_groups")
    except (OSError, ValueError, AttributeError) as exc:  # missing; not JSON (a ValueError); not a JSON object
        raise Unreadable(f"state.json: {exc}") from None
    if version_of(path) != state["version"]:
        raise Unreadable(f"state.json says version {state['version']}, the directory {path.name}")
    return state


def _apply(path: Path, loaded: tuple[dict, dict, dict], model: torch.nn.Module, optimizer: Any,
           generators: dict[str, torch.Generator],
           extra: Callable[[dict[str, torch.Tensor]], None] | None = None) -> Restored:
    state, arrays, tensors = loaded
    own = {key[len("algo."):]: value for key, value in tensors.items() if key.startswith("algo.")}
    if own and extra is None:
        raise ValueError(f"checkpoint {path}: holds an algorithm's state ({', '.join(sorted(own)[:3])}) this run "
                         "has no use for: another algo.name's checkpoint")
    if extra is not None:
        try:
            extra(own)
        except (ValueError, KeyError, RuntimeError) as exc:
            raise ValueError(f"checkpoint {path}: the algorithm's state does not fit: {exc}") from None
    load_arrays(model, arrays, source=f"policy checkpoint {path / 'policy.safetensors'}")
    slots: dict[int, dict[str, Any]] = {}
    for key, value in tensors.items():
        if key.startswith("opt."):
            _, index, name = key.split(".", 2)
            slots.setdefault(int(index), {})[name] = value
    try:
        optimizer.load_state_dict({"state": slots, "param_groups": state["param_groups"]})
    except (ValueError, KeyError) as exc:
        raise ValueError(f"checkpoint {path}: optimizer state does not fit this model: {exc}") from None
    for key, gen in generators.items():
        if f"rng.{key}" in tensors:
            gen.set_state(tensors[f"rng.{key}"])
    torch.set_rng_state(tensors["rng.torch"])
    return Restored(version=state["version"], path=path)


def _listdir(root: Path) -> list[Path]:
    try:
        return list(root.iterdir())
    except FileNotFoundError:
        return []
