"""The whole config (:class:`Config`: every section) and the rules that tie sections together."""

from __future__ import annotations

import dataclasses
import ipaddress
from dataclasses import dataclass, field
from typing import Any

from ebrl.config.base import ConfigError, Section
from ebrl.config.observers import VizSection, LogSection, EvalSection
from ebrl.config.rollout import EnvSection, SimSection, PolicySection, GenSection
from ebrl.config.run import RunSection, BusSection, HostEntry
from ebrl.config.training import AlgoSection, TrainSection, ReplaySection, AllocSection
from ebrl.envs import records
from ebrl.presets import PRESETS


SECTIONS: dict[str, type[Section]] = {cls.NAME: cls for cls in (
    RunSection, BusSection, EnvSection, SimSection, PolicySection, GenSection, AlgoSection, TrainSection,
    ReplaySection, AllocSection, VizSection, LogSection, EvalSection)}


@dataclass
class Config:
    run: RunSection = field(default_factory=RunSection)
    bus: BusSection = field(default_factory=BusSection)
    env: EnvSection = field(default_factory=EnvSection)
    sim: SimSection = field(default_factory=SimSection)
    policy: PolicySection = field(default_factory=PolicySection)
    gen: GenSection = field(default_factory=GenSection)
    algo: AlgoSection = field(default_factory=AlgoSection)
    train: TrainSection = field(default_factory=TrainSection)
    replay: ReplaySection = field(default_factory=ReplaySection)
    alloc: AllocSection = field(default_factory=AllocSection)
    viz: VizSection = field(default_factory=VizSection)
    log: LogSection = field(default_factory=LogSection)
    eval: EvalSection = field(default_factory=EvalSection)
    hosts: dict[str, HostEntry] = field(default_factory=dict)  # [hosts.<name>]: which services run where

    @property
    def num_envs(self) -> int:
        """Envs of one sim service (one host)."""
        return self.sim.groups * self.sim.envs_per_group

    @property
    def rollout_length(self) -> int:
        """Chunk decisions of each env per iteration (one policy update consumes one iteration) with one sim
        host; with n live sim hosts, 1/n of it (``Schedule.length``)."""
        return self.train.batch_size // self.num_envs

    def to_dict(self) -> dict[str, dict[str, Any]]:
        return dataclasses.asdict(self)


def train_ranks(cfg: Config) -> dict[str, range]:
    """The training ranks of each ``[hosts]`` entry that runs train, numbered across hosts in table order (the
    first holds rank 0: the primary); one host's: all of them."""
    owners = [name for name, entry in cfg.hosts.items() if "train" in entry.services]
    given = sum(cfg.hosts[name].ranks for name in owners)
    shares = sum(1 for name in owners if not cfg.hosts[name].ranks)  # these split what the others leave
    counts = [cfg.hosts[name].ranks or max(0, cfg.train.world_size - given) // max(1, shares) for name in owners]
    out, first = {}, 0
    for name, count in zip(owners, counts):
        out[name], first = range(first, first + count), first + count
    return out


def _check_train_hosts(cfg: Config) -> None:
    """Training ranks on several hosts: their shares, the rendezvous, what the run lacks for them."""
    ranks = train_ranks(cfg)
    if len(ranks) < 2:
        return
    shares = ", ".join(f"{name}: {len(r)}" for name, r in ranks.items())
    if sum(len(r) for r in ranks.values()) != cfg.train.world_size or any(len(r) == 0 for r in ranks.values()):
        raise ConfigError(f"train.world_size = {cfg.train.world_size}: the hosts that run train hold {shares} "
                          "ranks; give each host at least one and hosts.<name>.ranks that add up to it")
    host, _, port = cfg.train.rendezvous.rpartition(":")
    if not host or not port.isdigit():
        raise ConfigError(f"train.rendezvous = {cfg.train.rendezvous!r}: training on several hosts ({shares}) "
                          "needs HOST:PORT on the primary host where the ranks meet")
    if not cfg.train.trusted_networks:
        raise ConfigError("train.trusted_networks: training on several hosts sends gradients over "
                          "torch.distributed, which has no authentication or encryption of its own; name the "
                          "networks (CIDR) it may use, a private network between the hosts")
    for network in cfg.train.trusted_networks:
        try:
            ipaddress.ip_network(network, strict=False)
        except ValueError as exc:
            raise ConfigError(f"train.trusted_networks: {exc}") from None
    if cfg.alloc.enabled:
        raise ConfigError("alloc.enabled: the allocator plans one host's training; with ranks on several hosts set "
                          "alloc.enabled = false")


def vectorized(cfg: Config) -> bool:
    """Whether each sim group is one vectorized process (``sim.vectorized``; "auto": where physics is on the GPU;
    always for a backend whose group is one batch by nature, MuJoCo Warp's model of many worlds): the backend's
    record decides (``ebrl.envs.records``)."""
    return records.backend_record(cfg.env.backend).vectorized(cfg.sim.vectorized, cfg.env.kwargs)


def check_across(cfg: Config) -> None:
    """The rules that tie sections together (each section checked its own: :meth:`Section.check`)."""
    _check_batching(cfg)
    _check_vectorized(cfg)
    if cfg.sim.cores_per_env > 1 and cfg.sim.core_rebinding is True:
        raise ConfigError(f"sim.cores_per_env = {cfg.sim.cores_per_env}: pins each env worker to a set of cores, "
                          "which sim.core_rebinding = true does not use (rebinding hands out single cores); set "
                          "sim.cores_per_env = 1, or leave sim.core_rebinding to the mode")
    _check_processes(cfg)
    _check_algorithm(cfg)
    _check_train_hosts(cfg)
    if cfg.algo.name == "grpo":
        envs = cfg.num_envs
        if cfg.algo.group_size < 2 or envs % cfg.algo.group_size:
            raise ConfigError(f"algo.group_size = {cfg.algo.group_size}: grpo needs at least 2 rollouts per group "
                              f"and the {envs} envs (sim.groups x sim.envs_per_group) to split into whole groups")
        if not (PRESETS[cfg.run.mode]["overlap"] if cfg.train.overlap is None else cfg.train.overlap):
            raise ConfigError(f"algo.name = \"grpo\" with run.mode = {cfg.run.mode!r}: grpo learns from whole "
                              "episodes, which a rollout -> train barrier of fixed length cannot wait for; use "
                              "run.mode = \"ebrl\" or \"async\" (or train.overlap = true)")


def _check_algorithm(cfg: Config) -> None:
    """The algorithm against the policy it trains and the ranks that train it."""
    from ebrl.policies.registry import config_problem  # a registered kind's facts, no policy imported
    if problem := config_problem(cfg.policy, cfg.algo.name):  # a user's kind: checked by the launcher's preflight
        raise ConfigError(problem)
    if cfg.algo.name == "sac" and cfg.train.world_size > 1:
        raise ConfigError(f"train.world_size = {cfg.train.world_size}: sac trains on one rank (its replay is one "
                          "process's); set train.world_size = 1")


def processes(cfg: Config) -> list[list[str]]:
    """``run.processes`` as lists (``"auto"``, before the launcher decided it: none shared)."""
    return [] if cfg.run.processes == "auto" else cfg.run.processes


def _check_processes(cfg: Config) -> None:
    """``run.processes`` against the services the run has and where they run."""
    shared = {role for group in processes(cfg) for role in group}
    if "train" in shared and cfg.train.world_size > 1:
        raise ConfigError(f"run.processes: train with train.world_size = {cfg.train.world_size}: each training "
                          "rank runs in a process of its own; share a process only with one rank")


def _check_batching(cfg: Config) -> None:
    """An update's batch against the envs that fill it and the ranks that split it."""
    if cfg.train.batch_size % cfg.num_envs:
        raise ConfigError(f"train.batch_size = {cfg.train.batch_size}: must be a multiple of the number of envs "
                          f"(sim.groups x sim.envs_per_group = {cfg.num_envs}); each env runs batch_size / envs "
                          "decisions per iteration")
    if cfg.train.world_size > 1 and cfg.train.batch_size // cfg.train.world_size < cfg.algo.minibatches:
        raise ConfigError(f"train.world_size = {cfg.train.world_size}: each rank's share of train.batch_size "
                          f"({cfg.train.batch_size}) must hold algo.minibatches ({cfg.algo.minibatches}) decisions")


def _check_vectorized(cfg: Config) -> None:
    """What a vectorized group (one process stepping its envs as one batch) cannot do."""
    record = records.backend_record(cfg.env.backend)
    if record.vectorize == "always" and cfg.sim.vectorized is False:
        raise ConfigError(f"sim.vectorized = false: {record.always_vectorized}")
    if not vectorized(cfg):
        return
    if cfg.alloc.enabled:
        raise ConfigError("alloc.enabled: the allocator profiles the simulator as one env per worker process, and "
                          "sim.vectorized runs a group's envs as one batch (GPU PhysX groups are vectorized by "
                          "default); set alloc.enabled = false, or sim.vectorized = false")
    if cfg.sim.cores_per_env > 1:
        raise ConfigError(f"sim.cores_per_env = {cfg.sim.cores_per_env}: pins each env worker to a set of cores, "
                          "which sim.vectorized does not use (a vectorized group runs on the whole budget); set "
                          "sim.cores_per_env = 1")
    if cfg.algo.name == "grpo":
        raise ConfigError("sim.vectorized: grpo needs group-mates reset to the same initial state, which a "
                          "vectorized batch's partial resets cannot promise; set sim.vectorized = false (GPU PhysX "
                          "groups are vectorized by default)")
