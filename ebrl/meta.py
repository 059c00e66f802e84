"""``RUN_DIR/meta.json``: what a run needs to be reproduced — code, packages, machine, seeds, command, start time.

Written by the launcher before any service starts (:func:`write`); the log service
reads it back and hands it to the tracking sinks. Nothing here imports torch or a
simulator: versions come from the installed distributions' metadata, GPUs from
NVML (``ebrl.resources``), so collecting costs a few milliseconds.
"""

from __future__ import annotations

import datetime
import json
import os
import platform
import socket
import subprocess
import sys
import time
from importlib import metadata
from pathlib import Path
from typing import Any

import psutil

import ebrl
from ebrl import config as config_mod, durable

FILENAME = "meta.json"
# distributions whose versions decide what a run does (missing ones are reported as null)
PACKAGES = ("ebrl", "torch", "numpy", "gymnasium", "mujoco", "eclipse-zenoh", "msgpack", "robosuite", "mink",
            "safetensors", "tensorboard", "rerun-sdk", "wandb", "mani-skill", "sapien", "psutil", "nvidia-ml-py")
GEN_SEED_STRIDE = 1_000_003  # gen/<i> samples from torch.manual_seed(run.seed * stride + 1 + i)


def gen_seed(run_seed: int, instance: int) -> int:
    """The seed of generation instance ``instance``'s sampling: fixed by ``run.seed``, different per instance and
    from training's (which seeds with ``run.seed`` itself)."""
    return run_seed * GEN_SEED_STRIDE + 1 + instance


def seeds(cfg: config_mod.Config) -> dict[str, Any]:
    """Every seed the run uses, as derived from ``run.seed`` (``ebrl.sched.fleet``, ``ebrl/services/gen.py``,
    ``ebrl.algos.learner``)."""
    from ebrl.envs.worker import EPISODE_SEED_STRIDE
    from ebrl.sched.fleet import ENV_SEED_STRIDE

    return {
        "run": cfg.run.seed,
        "env": f"env i, episode k: reset(seed = {cfg.run.seed} * {ENV_SEED_STRIDE} + i + {EPISODE_SEED_STRIDE} * k)"
               + (f"; i is the first env of its group of {cfg.algo.group_size} (grpo)" if cfg.algo.name == "grpo"
                  else ""),
        "gen": {str(i): gen_seed(cfg.run.seed, i) for i in range(1)},
        "train": cfg.run.seed,
    }


def package_versions(names: tuple[str, ...] = PACKAGES) -> dict[str, str | None]:
    out: dict[str, str | None] = {}
    for name in names:
        try:
            out[name] = metadata.version(name)
        except metadata.PackageNotFoundError:
            out[name] = None
    return out


def git_state(path: str | Path | None = None) -> dict[str, Any] | None:
    """Commit, branch and whether the checkout that holds ``path`` (default: the ebrl package) has uncommitted
    changes; None outside a git checkout or without git."""
    where = Path(path) if path is not None else Path(ebrl.__file__).resolve().parent

    def git(*args: str) -> str:
        return subprocess.run(["git", "-C", str(where), *args], capture_output=True, text=True, timeout=10,
                              check=True).stdout.strip()

    try:
        commit = git("rev-parse", "HEAD")
        status = git("status", "--porcelain", "--untracked-files=no")
        branch = git("rev-parse", "--abbrev-ref", "HEAD")
        root = git("rev-parse", "--show-toplevel")
    except (OSError, subprocess.SubprocessError):
        return None
    return {"commit": commit, "branch": branch, "dirty": bool(status),
            "changed_files": len(status.splitlines()), "root": root}


def cpu_model() -> str:
    try:
        with open("/proc/cpuinfo") as fh:
            for line in fh:
                if line.startswith("model name"):
                    return line.split(":", 1)[1].strip()
    except OSError:
        pass
    return platform.processor() or platform.machine()


def machine() -> dict[str, Any]:
    from ebrl.resources.nvml import load_nvml
    from ebrl.resources.pool import discover_gpus

    try:
        gpus = [{"index": g.index, "name": g.name, "uuid": g.uuid, "memory_gib": round(g.memory_bytes / 2**30, 1),
                 "mig": g.mig_enabled} for g in discover_gpus(load_nvml(), None)]
    except Exception as exc:  # a broken driver is worth a note, not a failed run
        gpus = [{"error": str(exc)}]
    return {
        "hostname": socket.gethostname(),
        "platform": platform.platform(),
        "cpu_model": cpu_model(),
        "cpu_count": os.cpu_count(),
        "cores_usable": len(os.sched_getaffinity(0)),
        "memory_gib": round(psutil.virtual_memory().total / 2**30, 1),
        "gpus": gpus,
    }


def command_line() -> list[str]:
    """This process's command line as the user typed it: ``ebrl up ...`` (also under ``python -m ebrl.cli``), or
    ``python train.py ...`` for a script that called ``ebrl.train``."""
    program = Path(sys.argv[0]).name
    if program in ("ebrl", "cli.py", "__main__.py"):
        return ["ebrl", *sys.argv[1:]]
    return ["python", *sys.argv] if program.endswith(".py") else list(sys.argv)


def collect(cfg: config_mod.Config, run_dir: str | Path, argv: list[str] | None = None,
            started: float | None = None) -> dict[str, Any]:
    """The content of ``meta.json``."""
    started = time.time() if started is None else started
    return {
        "run": cfg.run.name,
        "run_dir": str(Path(run_dir).resolve()),
        "ebrl_version": ebrl.__version__,
        "git": git_state(),
        "command": command_line() if argv is None else argv,
        "cwd": os.getcwd(),
        "started_at": datetime.datetime.fromtimestamp(started, datetime.timezone.utc).isoformat(),
        "started_at_epoch": started,
        "mode": cfg.run.mode,
        "seeds": seeds(cfg),
        "python": sys.version.split()[0],
        "python_executable": sys.executable,
        "packages": package_versions(),
        "machine": machine(),
    }


def write(cfg: config_mod.Config, run_dir: str | Path, argv: list[str] | None = None,
          extra: dict[str, Any] | None = None) -> Path:
    """Write ``RUN_DIR/meta.json`` (a resumed run keeps the first start's and lists each later one, with
    ``extra``, under ``resumed``); return its path."""
    path = Path(run_dir) / FILENAME
    meta = {**collect(cfg, run_dir, argv), **(extra or {})}
    if path.exists():
        try:
            first = json.loads(path.read_text())
            meta = {**first, "resumed": [*first.get("resumed", []), meta]}
        except (OSError, ValueError):
            pass
    return durable.write_text(path, json.dumps(meta, indent=2) + "\n")


def read(run_dir: str | Path) -> dict[str, Any]:
    """``RUN_DIR/meta.json``, or {} when there is none (a run of an older EBRL)."""
    try:
        return json.loads((Path(run_dir) / FILENAME).read_text())
    except (OSError, ValueError):
        return {}
