"""Everything ``ebrl up`` does before the first process starts, as one value (:class:`PreparedRun`).

In order: the config and this host's part of the run (``ebrl.hosts``), the preflight (what would make the run
fail at start: a bus endpoint, a device, a missing policy file, an environment that cannot run here), what
``"auto"`` becomes on this machine (``ebrl.autotune``), with the allocator an MPS control daemon and the
initial plan (``ebrl.alloc.runtime``), the run directory (new, or ``--resume``'s), the bus secret, and the
resolved ``config.toml`` and ``meta.json`` the services and reports read. Anything that stops the run here
raises :class:`NotStarted` with the line to print: nothing was started (an MPS daemon started for the run is
quit again). :mod:`ebrl.launch` then only wires the processes, the run's view and the hosts.
"""

from __future__ import annotations

import dataclasses
import grp
import os
import sys
import time
from pathlib import Path
from typing import Any

from ebrl import autotune, config as config_mod, devices, durable, meta, ranknet, slurm, tracking
from ebrl.bus import auth
from ebrl.bus.endpoints import config_file_acl, config_file_endpoints
from ebrl.bus.joincheck import certificate_problem
from ebrl.envs.records import backend_record
from ebrl.hosts import HostPlan, decide_processes, plan as plan_host
from ebrl.policies.registry import preflight as policy_preflight


class NotStarted(Exception):
    """The run cannot start; the message is the line to print after ``ebrl: `` (exit code 2)."""


@dataclasses.dataclass
class PreparedRun:
    """A run ready to start on this host: its resolved config, this host's part, its directory, each stage's
    CUDA environment (the allocator's GPU shares), start-up events for the run's log, and an MPS control
    daemon this run started (quit by :meth:`close`)."""

    cfg: config_mod.Config
    plan: HostPlan
    run_dir: Path
    gpu_env: dict[str, dict[str, str]]
    notes: list[tuple[str, str]]
    mps: Any = None

    def close(self) -> None:
        """After every service (an MPS client) has exited: quit the MPS daemon this run started."""
        if self.mps is not None:
            print("ebrl: MPS control daemon " + ("quit" if self.mps.quit() else f"did not quit ({self.mps.pipe_dir})"),
                  file=sys.stderr)
            self.mps = None


def prepare(config_path: str, overrides: list[str], *, viz: str | None = None, resume: str | None = None,
            only: str | None = None, host: str | None = None, instance: int | None = None) -> PreparedRun:
    """The steps of the module docstring. ``viz`` (``--viz``) sets ``viz.rerun``; ``resume`` (``--resume
    RUN_DIR``) continues that run; ``only``/``instance`` or ``host`` start this host's part of a run over
    several hosts. Prints what the user should see on the way (the "auto" decision, the allocator's plan)."""
    if viz is not None:
        overrides = [*overrides, f'viz.rerun="{viz}"']
    try:
        cfg = config_mod.load(config_path, overrides)
        cfg, host = slurm.placement(cfg, host, only, instance)  # under srun: this task's [hosts] entry
        cfg, plan = plan_host(cfg, only=only, host=host, instance=instance)
    except config_mod.ConfigError as exc:
        raise NotStarted(f"config error: {exc}") from None
    if problem := preflight(cfg, tuple(plan.roles), plan.multi):
        raise NotStarted(problem)
    try:
        ranknet.across_hosts(cfg, plan)  # training ranks on several hosts: only over a trusted network
    except ValueError as exc:
        raise NotStarted(str(exc)) from None
    earlier = meta.read(resume).get("auto", {}).get("settings") if resume else None  # a resumed run keeps its own
    cfg, decision = autotune.settle(cfg, tuple(plan.roles), plan.multi, earlier)  # policy.dtype, gen.compile, ...
    if decision is not None and decision.line:
        print(decision.line, flush=True)
    notes = [("auto", decision.line)] if decision is not None and decision.line else []
    gpu = cfg.run.processes == "auto" and autotune.host_has_gpu()
    cfg, placed = decide_processes(cfg, plan, gpu)  # run.processes: written into config.toml with the rest
    if placed and (gpu or cfg.run.processes):  # a CPU host where nothing shares: said nowhere but config.toml
        print(placed, flush=True)
        notes.append(("auto", placed))
    run = PreparedRun(cfg, plan, Path(), {}, notes)
    try:
        if "alloc" in plan.roles:  # profile (or reuse a profile) and start every service inside Algorithm 1's plan
            allocate(run)
        run.run_dir = run_directory(run.cfg, resume, run.plan)
        if secret := auth.secret_path(run.cfg.bus, run.run_dir):
            shared_secret(run, Path(secret))
    except NotStarted:
        run.close()
        raise
    durable.write_text(run.run_dir / "config.toml", config_mod.dump_toml(run.cfg))
    # a resumed run's env steps go on from where its tracking stopped
    extra = {"env_steps_before": tracking.steps_so_far(run.run_dir)} if resume else {}
    extra = {**extra, "auto": decision.to_dict()} if decision else extra
    meta.write(run.cfg, run.run_dir, extra={**extra, "processes": run.cfg.run.processes})
    return run


def shared_secret(run: PreparedRun, secret: Path) -> None:
    """The run's secret file, checked, or made where this host may make it: on one host, or on the primary of
    several (said: every other host needs a copy). A host that joins another's run never makes one: a new secret
    could never sign in there."""
    if run.plan.multi and not secret.exists():
        if not run.plan.primary:
            raise NotStarted(f"bus.secret_file = {str(secret)!r}: no such file; a host that joins a run signs in "
                             "with the primary host's secret: copy that file here (mode 0600)")
        print(f"ebrl: wrote a new secret for the run at {secret}: copy it to every other host (mode 0600)",
              flush=True)
    try:
        auth.ensure(secret)  # before the first line: a script that read RUN_DIR from it finds the secret
    except (OSError, auth.AuthError) as exc:
        raise NotStarted(str(exc)) from None


def allocate(run: PreparedRun) -> None:
    """With ``alloc.gpu_pool = "mps"``, an MPS daemon for the run; the allocator's initial plan written into
    ``run.cfg``, and each stage's CUDA environment (the plan's line printed)."""
    from ebrl.alloc.algorithm import InfeasibleError
    from ebrl.alloc.runtime import initial_config
    from ebrl.resources.pool import ResourceError

    try:
        run.mps = start_mps(run.cfg)
        run.cfg, run.gpu_env, line = initial_config(run.cfg, local_sim="sim" in run.plan.roles)
    except (InfeasibleError, ResourceError) as exc:
        raise NotStarted(f"allocator: {exc}") from None
    print(line, flush=True)


def run_directory(cfg: config_mod.Config, resume: str | None, plan: HostPlan | None = None) -> Path:
    """A new run directory, or ``resume``'s when it holds a checkpoint to go on from. A host of several other
    than the primary names its own after itself: on a shared filesystem the hosts' directories sit side by
    side."""
    if resume is None:
        tag = f"-{plan.name or f'host{plan.instance}'}" if plan is not None and plan.multi and not plan.primary else ""
        return make_run_dir(cfg, tag)
    from ebrl.algos import checkpoint

    run_dir = Path(resume)
    found = checkpoint.latest(run_dir)
    if found is None:
        raise NotStarted(f"--resume {resume}: no checkpoint there ({run_dir / checkpoint.DIRNAME}/latest)")
    print(f"resuming {run_dir} from {found.name}", flush=True)
    return run_dir


def make_run_dir(cfg: config_mod.Config, tag: str = "") -> Path:
    """A new directory for the run, only its owner's (0700), or its owner's and ``run.group``'s (0750): made so
    from the start, never readable by others in between. ``tag`` ends its name (a host's)."""
    stamp = time.strftime("%Y%m%d-%H%M%S")
    Path(cfg.run.output_dir).mkdir(parents=True, exist_ok=True)
    suffix = 0
    while True:  # another launcher may take a name between a look and the mkdir (hosts on a shared filesystem)
        run_dir = Path(cfg.run.output_dir) / (f"{cfg.run.name}-{stamp}{tag}" + (f"-{suffix}" if suffix else ""))
        try:
            run_dir.mkdir(mode=0o700)
            break
        except FileExistsError:
            suffix += 1
    if cfg.run.group:
        try:
            os.chown(run_dir, -1, grp.getgrnam(cfg.run.group).gr_gid)
        except (KeyError, PermissionError) as exc:
            run_dir.rmdir()
            why = "no such group" if isinstance(exc, KeyError) else "you are not one of its members"
            raise NotStarted(f"run.group = {cfg.run.group!r}: {why}") from None
        run_dir.chmod(0o750)
    (run_dir / "logs").mkdir()
    return run_dir




def check_bus_endpoints(cfg: config_mod.Config) -> str | None:
    """Every endpoint Zenoh will use (bus.listen, bus.connect and those of bus.config_file): plain ones that
    leave the host refused unless bus.insecure (then a warning). A config file's own access control is refused
    where EBRL signs the run in (bus.auth), rather than silently replaced by EBRL's rules."""
    try:
        endpoints = config_file_endpoints(cfg.bus.config_file)
        file_acl = config_file_acl(cfg.bus.config_file)
    except Exception as exc:  # zenoh.ZError: the file does not parse
        return f"bus.config_file = {cfg.bus.config_file!r}: {exc}"
    if file_acl and cfg.bus.auth:
        return (f"bus.config_file = {cfg.bus.config_file!r} turns on access_control, and with bus.auth EBRL sets "
                "the run's own (observers only read); it cannot merge the two: remove the block from the file, or "
                "set bus.auth = false to run with yours alone")
    endpoints += [*cfg.bus.listen, *cfg.bus.connect]
    if refused := auth.check_endpoints(endpoints, cfg.bus.insecure, "bus"):
        return refused
    if missing := certificate_problem(cfg.bus.config_file):
        return missing
    if cfg.bus.insecure and (plain := auth.insecure_endpoints(endpoints)):
        print(f"ebrl: warning: bus.insecure = true: {', '.join(plain)} carry the run's data unencrypted beyond "
              "this host", file=sys.stderr)
    return None


def preflight(cfg: config_mod.Config, roles: tuple[str, ...] = ("gen", "train"), multi: bool = False) -> str | None:
    """What would make the run fail at start, found before any process starts (None: nothing); ``roles``: the
    services this host runs; ``multi``: one host of several."""
    from ebrl.envs import EnvError, EnvSpec, preflight as env_preflight

    if problem := check_bus_endpoints(cfg):
        return problem
    if multi and cfg.bus.auth and not cfg.bus.secret_file:
        return ("a run over several hosts needs one secret on every host: create it with `ebrl secret PATH`, copy it "
                "to each host (mode 0600) and set bus.secret_file = PATH (or bus.auth = false on a trusted network)")
    if cfg.policy.checkpoint and not os.path.isfile(cfg.policy.checkpoint):
        return f"policy.checkpoint = {cfg.policy.checkpoint!r}: no such file"
    if problem := policy_preflight(cfg.policy, cfg.algo.name):  # a user's kind imports, is a ChunkPolicy, fits
        return problem
    device_error = devices.preflight(cfg, roles)  # e.g. train.device = "cuda" on a machine without one
    if device_error:
        return device_error
    if "log" in roles and (wandb_error := tracking.wandb_problem(cfg.log)):  # not installed, not logged in
        return wandb_error
    try:
        env_preflight(EnvSpec.from_config(cfg.env))  # e.g. ManiSkill without a GPU; picks the GL backend for cameras
    except EnvError as exc:
        return str(exc)
    if "sim" in roles:
        return too_many_processes(cfg, len(os.sched_getaffinity(0)))
    return None


PROCESSES_PER_CORE = 8  # env worker processes per core beyond which a run is refused (ManiSkill on CPU PhysX)


def too_many_processes(cfg: config_mod.Config, cores: int) -> str | None:
    """ManiSkill configs are sized for GPU PhysX (hundreds of envs, one process per group); where CPU PhysX runs
    them instead (``sim_backend = "auto"`` without CUDA torch), each env would be a process of its own. The
    backends whose configs are so sized say what runs instead (their records' ``on_cpu``)."""
    on_cpu = backend_record(cfg.env.backend).on_cpu
    if on_cpu is None or config_mod.vectorized(cfg) or cfg.num_envs <= PROCESSES_PER_CORE * cores:
        return None
    return (f"sim.envs_per_group = {cfg.sim.envs_per_group}: {cfg.num_envs} {on_cpu(cfg.env.kwargs)} would "
            f"start {cfg.num_envs} worker processes on {cores} cores; lower sim.envs_per_group (e.g. --set "
            f"sim.envs_per_group={max(1, PROCESSES_PER_CORE * cores // max(1, cfg.sim.groups))}), or run where "
            "torch sees a CUDA GPU")


def start_mps(cfg: config_mod.Config):
    """With ``alloc.gpu_pool = "mps"`` on a host with a GPU and no reachable MPS control daemon: start one for
    this run (``ebrl.resources.mps``); None otherwise."""
    if cfg.alloc.gpu_pool != "mps":
        return None
    from ebrl.resources.mps import MpsDaemon
    from ebrl.resources.nvml import load_nvml
    from ebrl.resources.pool import discover_gpus

    if not discover_gpus(load_nvml(), None):
        return None  # no GPU: the pool partitions cores only
    daemon = MpsDaemon.ensure(log_dir=Path(cfg.run.output_dir).resolve() / "mps-log")
    if daemon is not None:
        print(f"ebrl: started an MPS control daemon for this run ({daemon.pipe_dir})", flush=True)
    return daemon
