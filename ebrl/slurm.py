"""Runs on a cluster. On Slurm, ``ebrl slurm CONFIG`` writes (and with ``--submit`` submits) a batch script that
starts one ``ebrl up`` per allocated node, and ``ebrl up`` started by ``srun`` takes its part of the run from
Slurm's environment.

Under ``srun`` with several tasks, task *i* runs the *i*-th entry of the config's ``[hosts]`` table (as ``--host``
would), so the table has one entry per task; with one task the run is a one-host run. Node names are not known
before the job starts, so an endpoint of ``bus.listen``, ``bus.connect`` or a ``[hosts]`` entry may say
``{primary}`` (the node of the task that runs training rank 0; also in ``train.rendezvous``) or ``{node}`` (this task's own node); they are filled in
from ``SLURM_JOB_NODELIST`` and ``SLURM_TASKS_PER_NODE`` (:func:`placement`). Outside Slurm they are a config
error.

Under a Kubernetes Indexed Job, pod *i* (``JOB_COMPLETION_INDEX``) runs the *i*-th entry of ``[hosts]`` the same
way; pods have stable names there, so the config gives them (:func:`indexed_job`).
"""

from __future__ import annotations

import dataclasses
import os
import re
import shlex
import subprocess
import sys
from pathlib import Path
from typing import Mapping

from ebrl.config import Config, ConfigError

PLACEHOLDERS = ("{primary}", "{node}")


def expand_nodelist(expr: str) -> list[str]:
    """Slurm's host list syntax, expanded: ``node[01-03,07],gpu5`` -> node01, node02, node03, node07, gpu5."""
    names: list[str] = []
    for part in re.findall(r"[^,\[]+(?:\[[^\]]*\])?[^,]*", expr):
        match = re.fullmatch(r"([^\[]*)\[([^\]]*)\](.*)", part)
        if match is None:
            names.append(part)
            continue
        prefix, ranges, suffix = match.groups()
        for item in ranges.split(","):
            low, _, high = item.partition("-")
            if not high:
                names.append(f"{prefix}{low}{suffix}")
                continue
            if not (low.isdigit() and high.isdigit()) or int(high) < int(low):
                raise ValueError(f"not a Slurm host list: {expr!r} ({item!r})")
            names += [f"{prefix}{n:0{len(low)}d}{suffix}" for n in range(int(low), int(high) + 1)]
    return names


def tasks_per_node(expr: str) -> list[int]:
    """``SLURM_TASKS_PER_NODE`` expanded: ``2(x3),1`` -> [2, 2, 2, 1]."""
    counts: list[int] = []
    for item in expr.split(","):
        match = re.fullmatch(r"(\d+)(?:\(x(\d+)\))?", item.strip())
        if match is None:
            raise ValueError(f"not a Slurm task count: {expr!r}")
        counts += [int(match[1])] * int(match[2] or 1)
    return counts


def node_of_task(task: int, env: Mapping[str, str]) -> str:
    """The node task ``task`` runs on: Slurm's default (block) distribution over the job's nodes."""
    nodes = expand_nodelist(env.get("SLURM_JOB_NODELIST") or env.get("SLURM_NODELIST", ""))
    counts = tasks_per_node(env.get("SLURM_TASKS_PER_NODE", ",".join("1" for _ in nodes)))
    for node, count in zip(nodes, counts):
        if task < count:
            return node
        task -= count
    raise ValueError(f"task {task} is on no node of {nodes} ({env.get('SLURM_TASKS_PER_NODE')})")


def indexed_job(cfg: Config, host: str | None, only: str | None, instance: int | None,
                env: Mapping[str, str]) -> str | None:
    """Under a Kubernetes Indexed Job (``JOB_COMPLETION_INDEX`` set) with a ``[hosts]`` table: the entry of this
    pod's index, where the command line names no part; else ``host``."""
    if "JOB_COMPLETION_INDEX" not in env or not cfg.hosts or any(x is not None for x in (host, only, instance)):
        return host
    index = int(env["JOB_COMPLETION_INDEX"])
    if not 0 <= index < len(cfg.hosts):
        raise ConfigError(f"JOB_COMPLETION_INDEX = {index}: the config's [hosts] has {len(cfg.hosts)} entries "
                          f"({', '.join(cfg.hosts)}): one per index (completions = {len(cfg.hosts)})")
    return list(cfg.hosts)[index]


def under_srun(env: Mapping[str, str]) -> bool:
    """Whether this process is a task that ``srun`` started (a step's task has a rank in it)."""
    return "SLURM_PROCID" in env and "SLURM_STEP_ID" in env


def _endpoints(cfg: Config):
    """(where, list) for each endpoint list of the config that may carry a placeholder."""
    yield "bus.listen", cfg.bus.listen
    yield "bus.connect", cfg.bus.connect
    yield "train.rendezvous", [cfg.train.rendezvous]
    for name, entry in cfg.hosts.items():
        yield f"hosts.{name}.listen", entry.listen
        yield f"hosts.{name}.connect", entry.connect


def fill(cfg: Config, primary: str, node: str) -> Config:
    """``cfg`` with ``{primary}`` and ``{node}`` filled in wherever an endpoint says them."""
    def filled(values: list[str]) -> list[str]:
        return [v.replace("{primary}", primary).replace("{node}", node) for v in values]

    bus = dataclasses.replace(cfg.bus, listen=filled(cfg.bus.listen), connect=filled(cfg.bus.connect))
    hosts = {name: dataclasses.replace(e, listen=filled(e.listen), connect=filled(e.connect))
             for name, e in cfg.hosts.items()}
    train = dataclasses.replace(cfg.train, rendezvous=filled([cfg.train.rendezvous])[0])
    return dataclasses.replace(cfg, bus=bus, hosts=hosts, train=train)


def placement(cfg: Config, host: str | None, only: str | None, instance: int | None,
              env: Mapping[str, str] = os.environ) -> tuple[Config, str | None]:
    """This task's part of a run under ``srun``: the config with its placeholders filled in, and the ``[hosts]``
    entry it runs (None: a one-host run, or the part ``--host``/``--only`` named). Outside Slurm, only checks that
    no endpoint says a placeholder. ConfigError names what does not fit."""
    said = [where for where, values in _endpoints(cfg) if any(p in v for v in values for p in PLACEHOLDERS)]
    if not under_srun(env):
        if said:
            raise ConfigError(f"{said[0]}: {{primary}} and {{node}} are filled in only in a task that srun started "
                              "(ebrl slurm); give the address")
        return cfg, indexed_job(cfg, host, only, instance, env)
    tasks, rank = int(env.get("SLURM_NTASKS", "1")), int(env["SLURM_PROCID"])
    given = host is not None or only is not None or instance is not None
    if tasks > 1 and not given:
        if len(cfg.hosts) != tasks:
            raise ConfigError(f"under srun with {tasks} tasks, task i runs the i-th entry of [hosts]: the config "
                              f"has {len(cfg.hosts)} ({', '.join(cfg.hosts) or 'no [hosts] table'}); give it one "
                              "entry per task (the one with train is the primary)")
        host = list(cfg.hosts)[rank]
    primaries = [i for i, e in enumerate(cfg.hosts.values()) if "train" in e.services]  # the first holds rank 0
    try:
        node = node_of_task(rank, env)
        primary = node_of_task(primaries[0], env) if cfg.hosts and primaries and tasks > 1 else node
    except ValueError as exc:
        raise ConfigError(f"Slurm's environment: {exc}") from None
    return fill(cfg, primary, node), host


def output_dir(cfg: Config, cwd: str) -> Path:
    """Where the job's output goes: ``run.output_dir`` (from ``cwd``), which must exist when the job starts."""
    out = Path(cfg.run.output_dir).expanduser()
    return out if out.is_absolute() else Path(cwd) / out


def batch_script(config: str, cfg: Config, overrides: list[str], nodes: int, partition: str = "",
                 time_limit: str = "", python: str = sys.executable, cwd: str | None = None) -> str:
    """The ``sbatch`` script of a run: ``nodes`` nodes, one task each with every CPU of its node (as many as the
    first node has: a cluster of like nodes), the run's secret made once on the shared filesystem where the
    config asks for one, one ``ebrl up`` per node. Its output goes to ``run.output_dir`` (:func:`output_dir`:
    make it before submitting)."""
    if nodes > 1 and len(cfg.hosts) != nodes:
        raise ConfigError(f"--nodes {nodes}: node i runs the i-th entry of [hosts], and the config has "
                          f"{len(cfg.hosts)} ({', '.join(cfg.hosts) or 'no [hosts] table'}): one entry per node")
    if nodes == 1 and cfg.hosts:
        raise ConfigError(f"--nodes 1 with [hosts] ({', '.join(cfg.hosts)}): one node per entry (--nodes "
                          f"{len(cfg.hosts)})")
    cwd = cwd or os.getcwd()
    out = output_dir(cfg, cwd)
    up = [python, "-m", "ebrl.cli", "up", str(Path(cwd) / config),
          *[arg for value in overrides for arg in ("--set", value)]]
    roles = [f"{name} (the primary)" if "train" in e.services else name for name, e in cfg.hosts.items()]
    lines = ["#!/bin/bash",
             f"# EBRL run {cfg.run.name} on Slurm, written by `ebrl slurm {config}`: one `ebrl up` per node"]
    lines += [f"# node i runs [hosts] entry i: {', '.join(roles)}"] * bool(cfg.hosts)
    lines += [
             f"#SBATCH --job-name=ebrl-{cfg.run.name}",
             f"#SBATCH --nodes={nodes}",
             "#SBATCH --ntasks-per-node=1",
             "#SBATCH --exclusive",
             f"#SBATCH --output={out}/slurm-%j.out"]
    lines += [f"#SBATCH --partition={partition}"] * bool(partition) + [f"#SBATCH --time={time_limit}"] * bool(time_limit)
    lines += ["set -euo pipefail", f"cd {shlex.quote(cwd)}"]
    if cfg.bus.auth and cfg.bus.secret_file:
        secret = shlex.quote(str(Path(cfg.bus.secret_file).expanduser()))
        lines += ["# the run's secret, once, where every node reads it (a shared filesystem)",
                  f"[ -e {secret} ] || {{ mkdir -p \"$(dirname {secret})\" && {shlex.quote(python)} -m ebrl.cli "
                  f"secret {secret}; }}"]
    lines += ['srun --kill-on-bad-exit=1 --cpus-per-task="$SLURM_CPUS_ON_NODE" ' + shlex.join(up)]
    return "\n".join(lines) + "\n"


def submit(script: Path) -> str:
    """``sbatch SCRIPT``: the job id (its line); CalledProcessError with sbatch's message where it refuses."""
    done = subprocess.run(["sbatch", "--parsable", str(script)], capture_output=True, text=True, check=True)
    return done.stdout.strip().split(";")[0]
