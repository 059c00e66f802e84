"""Which services ``ebrl up`` starts on this host, and as which instances.

A run spans several hosts by starting ``ebrl up`` once per host, each with a
subset of the services: ``--only sim --instance 1`` on the command line, or
``--host NAME`` with a ``[hosts.NAME]`` table in the config that says what runs
where and how the hosts' buses meet (``listen`` on the host others connect to,
``connect`` on the rest, or every host connecting to an ``ebrl router``).

Each host has a number, its *instance*: its launcher is ``launcher/<n>`` and its
sim service ``sim/<n>``, whose group and env ids follow those of the hosts before
it, so ids are unique in the run. The host that runs ``train`` is the primary: it
ends the run (``run.iterations``, ``run.target_return``) and tells the other
hosts' launchers to stop.

While a run goes on, each launcher follows the run's liveliness tokens
(:class:`Membership`): which services are live, which other hosts joined and
left, and on a secondary host whether the primary is gone.
"""

from __future__ import annotations

import asyncio
import dataclasses
import time
from dataclasses import dataclass

from ebrl import graph, keys
from ebrl.config import ROLES, Config, ConfigError, processes, train_ranks, vectorized
from ebrl.envs.records import backend_record

PRIMARY_LOST_S = 30.0  # a secondary host stops when no train has been live for this long
WITH_TRAIN = tuple(name for name, role in graph.ROLES.items() if role.with_train)  # ebrl.graph.Role.with_train
UNKNOWN_KEPT = 4096  # tokens of instances the run does not have, remembered to count each once (memory bounded)


@dataclass(frozen=True)
class HostPlan:
    roles: tuple[str, ...]  # services started on this host, in start order
    instance: int = 0  # this host's number in the run
    multi: bool = False  # one host of several: the launcher routes bus traffic between hosts
    name: str = ""  # the [hosts] entry, if any
    ranks: range | None = None  # this host's training ranks where several hosts train (None: every rank)

    @property
    def primary(self) -> bool:
        """The host that ends the run: the one with training rank 0."""
        return "train" in self.roles and (self.ranks is None or 0 in self.ranks)

    @property
    def ranks_elsewhere(self) -> bool:
        """Training ranks also run on other hosts (they meet at ``train.rendezvous``)."""
        return self.ranks is not None

    def instances(self, role: str, cfg: Config) -> range:
        """Instances of ``role`` started here: sim/<host> and alloc/<host>, this host's train ranks (every rank
        where one host trains), one of the others."""
        if role in ("sim", "alloc"):
            return range(self.instance, self.instance + 1)
        if role == "train":
            return self.ranks if self.ranks is not None else range(cfg.train.world_size)
        return range(1)

    def processes(self, cfg: Config) -> list[tuple[tuple[str, int], ...]]:
        """The processes this host's launcher starts, in start order: each the service instances in it, ``(role,
        n)``, the first the one whose identity it signs in with. Services that ``run.processes`` groups (those of
        them the run has) share one; every other instance has its own. ConfigError where a group is split
        between this host and another."""
        shared: dict[str, tuple[tuple[str, int], ...]] = {}
        for group in processes(cfg):
            members = [role for role in self.roles if role in group]  # in start order
            wanted = [role for role in group if role in enabled_roles(cfg)]  # those the run has
            if members and set(members) != set(wanted):
                raise ConfigError(f"run.processes: {group} is split between hosts (this one runs {members} of "
                                  "them): the services of one process run on one host")
            if len(members) < 2:
                continue
            unit = tuple((role, n) for role in members for n in self.instances(role, cfg))
            shared.update({role: unit for role in members})
        units: list[tuple[tuple[str, int], ...]] = []
        for role in self.roles:  # each process where its first service starts
            if role not in shared:
                units += [((role, n),) for n in self.instances(role, cfg)]
            elif shared[role] not in units:
                units.append(shared[role])
        return units

    def started(self, cfg: Config) -> tuple[tuple[str, int], ...]:
        """Every service instance this host's launcher starts, ``(role, n)``: the ones its router admits, each
        with its own identity (``ebrl.bus.auth``)."""
        return tuple((role, n) for role in self.roles for n in self.instances(role, cfg))


def sim_hosts(cfg: Config, plan: HostPlan) -> tuple[int, ...] | None:
    """The simulator hosts the run has, by its plan: host 0 alone on one host; over ``[hosts]``, the number of
    each entry that runs sim. None for hosts that join with ``--only`` (their numbers are the launchers': any
    host whose launcher admits a simulator). Generation's batch and the iteration schedule count live simulators
    of these hosts only (``ebrl.bus.peers``), so a token of another instance changes neither."""
    if not plan.multi:
        return (plan.instance,)
    if cfg.hosts:
        return tuple(i for i, entry in enumerate(cfg.hosts.values()) if "sim" in entry.services)
    return None


def enabled_roles(cfg: Config) -> tuple[str, ...]:
    """Every service the run has, in start order (``ebrl.config.ROLES``: viz and log first, they see the run from
    its start; the replay before train, which asks it for minibatches; the allocator last, it only reads the
    others' stats): those whose switch in the graph (``ebrl.graph.Role.switch``) is on, and those without one."""
    try:
        return tuple(r for r in ROLES if (switch := graph.ROLES[r].switch) is None or switch.on(cfg))
    except ValueError as exc:  # a user's module:Class that does not import or is not an algorithm
        raise ConfigError(str(exc)) from None


def plan(cfg: Config, only: str | None = None, host: str | None = None, instance: int | None = None
         ) -> tuple[Config, HostPlan]:
    """The services this host starts (and the config they run with); ConfigError names what is wrong."""
    every = enabled_roles(cfg)
    if host is not None:
        if only is not None or instance is not None:
            raise ConfigError("--host takes this host's services and number from [hosts]; drop --only/--instance")
        if host not in cfg.hosts:
            known = ", ".join(cfg.hosts) or "none: the config has no [hosts] section"
            raise ConfigError(f"--host {host}: no [hosts.{host}] in the config (hosts: {known})")
        entry = cfg.hosts[host]
        named = {r for e in cfg.hosts.values() for r in e.services}
        ranks = train_ranks(cfg)
        # the services with_train go with train (rank 0's host) unless some host names them; the allocator always
        # does (it plans that host)
        wanted = set(entry.services) | (set(WITH_TRAIN) - named if 0 in ranks.get(host, ()) else set())
        _allocator_with_train(wanted, f"[hosts.{host}]")
        bus = dataclasses.replace(cfg.bus, listen=list(entry.listen or cfg.bus.listen),
                                  connect=list(entry.connect or cfg.bus.connect))
        sim = dataclasses.replace(cfg.sim, cores=list(entry.cores or cfg.sim.cores))
        cfg = dataclasses.replace(cfg, bus=bus, sim=sim)
        here = ranks.get(host) if len(ranks) > 1 else None
        return cfg, HostPlan(tuple(r for r in every if r in wanted), list(cfg.hosts).index(host), True, host, here)
    if cfg.hosts:
        raise ConfigError(f"the config has [hosts] ({', '.join(cfg.hosts)}): start each host with --host NAME")
    if only is None:
        if instance is not None:
            raise ConfigError("--instance numbers one host of several: use it with --only")
        return cfg, HostPlan(every)
    asked = [r.strip() for r in only.split(",") if r.strip()]
    for role in asked:
        if role not in ROLES:
            raise ConfigError(f"--only {only}: unknown service {role!r}; services are {', '.join(ROLES)}")
    missing = [r for r in asked if r not in every]
    if missing:
        settings = "; ".join(f"{r}: {graph.ROLES[r].switch.setting}" for r in missing if graph.ROLES[r].switch)
        raise ConfigError(f"--only {only}: {', '.join(missing)} is off in this config ({settings})")
    number = 0 if instance is None else instance
    if number < 0:
        raise ConfigError(f"--instance {number}: must be >= 0")
    # the services with_train go with training
    wanted = set(asked) | (set(WITH_TRAIN) if "train" in asked else set())
    _allocator_with_train(wanted, f"--only {only}")
    return cfg, HostPlan(tuple(r for r in every if r in wanted), number, True)


def _allocator_with_train(roles: set[str], where: str) -> None:
    if "alloc" in roles and "train" not in roles:
        raise ConfigError(f"{where}: the allocator (alloc) runs on the host that trains: it plans that host's "
                          "cores, reading every host's stats")


@dataclass(frozen=True)
class HostChange:
    """Another host's launcher came up (``joined``) or went away."""

    host: int
    joined: bool


class Membership:
    """The run's liveliness tokens as one host's launcher sees them: the processes that are live, the other
    hosts that joined and left, whether the primary host (its ``train``) is gone."""

    def __init__(self, run: str, me: int = 0, multi: bool = False, lost_after_s: float = PRIMARY_LOST_S):
        self.run, self.me, self.multi, self.lost_after_s = run, me, multi, lost_after_s
        self.live: set[str] = set()  # every live token of the run
        self.ever: set[str] = set()  # ... and every one that was live once (at most the planned instances')
        self.hosts_up: set[int] = set()  # the other hosts, while up
        self.hosts_joined: set[int] = set()  # ... and every one that ever joined
        self.ending = False  # this host is stopping: hosts that leave now are not news
        self.train_seen_at: float | None = None  # when a train was last live
        # the tokens of the run's instances (planned_instances), where its router passes on only theirs: any
        # other reached the router alone and is not taken in, only counted (unknown_seen, each time it appears)
        self.planned: frozenset[str] | None = None
        self.unknown: set[str] = set()
        self.unknown_seen = 0

    def admit_only(self, instances: tuple[tuple[str, int], ...]) -> None:
        """Take in only the tokens of ``instances`` from now on (see :attr:`planned`)."""
        self.planned = frozenset(graph.keys_of(self.run, role, n).token() for role, n in instances)

    def update(self, key: str, alive: bool) -> HostChange | None:
        """A token appeared or vanished; a change when it was another host's launcher."""
        if self.planned is not None and key not in self.planned:
            if alive and key not in self.unknown:
                self.unknown_seen += 1
            if not alive or len(self.unknown) < UNKNOWN_KEPT:  # past it, each appearance counts anew
                (self.unknown.add if alive else self.unknown.discard)(key)
            return None
        if alive:
            self.live.add(key)
            if self.planned is not None or len(self.ever) < UNKNOWN_KEPT:
                self.ever.add(key)
        else:
            self.live.discard(key)
        try:
            parsed = keys.parse(key)
        except ValueError:  # not a process's token: nothing to say about hosts
            return None
        if not (self.multi and parsed.service == "launcher" and parsed.instance.isdigit()):
            return None
        host = int(parsed.instance)
        if host == self.me:
            return None
        if alive and host not in self.hosts_up:
            self.hosts_up.add(host)
            self.hosts_joined.add(host)
            return HostChange(host, joined=True)
        if not alive and host in self.hosts_up and not self.ending:
            self.hosts_up.discard(host)
            return HostChange(host, joined=False)
        return None

    def is_live(self, role: str, instance: int | str) -> bool:
        return graph.keys_of(self.run, role, instance).token() in self.live

    async def number_taken(self, wait_s: float = 1.0) -> bool:
        """Whether another host's launcher already has this host's number; the other hosts' tokens arrive once
        the routers met, so it looks after ``wait_s``."""
        await asyncio.sleep(wait_s)
        return self.is_live("launcher", self.me)

    def gone(self, role: str, instances: range) -> list[int]:
        """Those of ``instances`` of ``role`` that were live once and are not now."""
        return [n for n in instances
                if graph.keys_of(self.run, role, n).token() in self.ever and not self.is_live(role, n)]

    def services_live(self) -> int:
        """Live service processes (launchers not counted)."""
        return sum(1 for k in self.live if keys.role_of(k) != "launcher")

    def hosts(self) -> list[int]:
        """Every host that took part: this one and each that joined."""
        return sorted(self.hosts_joined | {self.me})

    def primary_lost(self, now: float | None = None) -> bool:
        """A secondary host: True once no training rank 0 (the primary's) has been live for ``lost_after_s`` after
        one was."""
        now = time.monotonic() if now is None else now
        if self.is_live("train", 0):
            self.train_seen_at = now
            return False
        return self.train_seen_at is not None and now - self.train_seen_at >= self.lost_after_s


def decide_processes(cfg: Config, here: HostPlan, gpu: bool) -> tuple[Config, str]:
    """``cfg`` with ``run.processes = "auto"`` decided for this host (``gpu``: it has one), and the line that says
    what it became ("" where it was not "auto").

    - On a GPU host: sim, gen and train in one process, where this host runs the three with one training rank,
      no allocator (its quotas and GPU shares are a process's each) and a GPU simulator (its record's
      ``gpu_simulator``, ebrl.envs.records) on a task EBRL ships (no ``module:EnvId``: a user's env code never shares
      training's memory unasked), so that the three stages share one CUDA context and no message between them
      leaves the process.
    - On a CPU host: sim and gen in one process, where this host runs both in the ebrl mode (the baselines keep
      the process layout they model) without the allocator, each env steps in a worker process of its own (not
      ``sim.vectorized``: the env's code never runs in the shared process beyond describing it once, and gen's
      policy is nothing the simulator could not already act against) and the env is not a ``module:EnvId``.
      Their observations and actions then go by reference instead of through the launcher's router: 1.25x the
      quickstart's env steps/s on 2 cores, HalfCheetah's unchanged (0.99x; BENCHMARKS.md, "The CPU default: sim
      and gen in one process"); training keeps its own process, and with it its cores.
    - Else every service alone.

    The replay (an off-policy run's) shares train's process wherever this host runs both with one training
    rank: its minibatches are then handed over by reference (BENCHMARKS.md, "Where the replay runs")."""
    if cfg.run.processes != "auto":
        return cfg, ""
    stages = ["sim", "gen", "train"] if gpu else ["sim", "gen"]
    why = ("not every stage on this host" if not set(stages) <= set(here.roles)
           else "the allocator shares cores and the GPU out per process" if cfg.alloc.enabled
           else _why_apart_on_gpu(cfg) if gpu else _why_apart_on_cpu(cfg))
    chosen = [] if why else [stages]
    replay = {"train", "replay"} <= set(here.roles) and cfg.train.world_size == 1
    if replay:
        chosen = [group + ["replay"] for group in chosen if "train" in group] or chosen + [["train", "replay"]]
    cfg = dataclasses.replace(cfg, run=dataclasses.replace(cfg.run, processes=chosen))
    shared = ("a GPU simulator, generation and training on one GPU" if gpu
              else "no GPU on this host: the simulator and generation")
    reasons = [why or shared] + ["the replay with training"] * replay
    return cfg, f"auto: run.processes = {chosen} ({'; '.join(reasons)})"


def _why_apart_on_gpu(cfg: Config) -> str:
    """Why sim, gen and train keep their processes on a GPU host ("": they share one)."""
    simulator = backend_record(cfg.env.backend)
    return (f"env.backend = {cfg.env.backend!r} steps on the CPU" if not simulator.gpu_simulator
            else f"env.id = {cfg.env.id!r} is your own code" if not simulator.ships(cfg.env.id)
            else "several training ranks" if cfg.train.world_size > 1
            else "")


def _why_apart_on_cpu(cfg: Config) -> str:
    """Why sim and gen keep their processes on a CPU host ("": they share one)."""
    return (f"run.mode = {cfg.run.mode!r} keeps its own layout" if cfg.run.mode != "ebrl"
            else "no GPU on this host; the vectorized groups keep their processes" if vectorized(cfg)
            else f"no GPU on this host; env.id = {cfg.env.id!r} is your own code" if ":" in cfg.env.id
            else "")


def planned_instances(cfg: Config, here: HostPlan) -> tuple[tuple[str, int], ...] | None:
    """Every process instance the run has on every host, ``(role, n)`` with each host's launcher: this host's
    alone on one host, each ``[hosts]`` entry's over several. None for hosts that join with ``--only`` (no plan
    names the others). A client-mode router passes liveliness tokens on only for these
    (``ebrl.graph.access_control``); its launcher counts any other as ``launcher/unknown_instances``."""
    if not here.multi:
        return here.started(cfg) + (("launcher", here.instance),)
    if not cfg.hosts:
        return None
    every: list[tuple[str, int]] = []
    for name in cfg.hosts:
        host_cfg, host_plan = plan(cfg, host=name)
        every += [*host_plan.started(host_cfg), ("launcher", host_plan.instance)]
    return tuple(every)
