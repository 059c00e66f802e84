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
"""

from __future__ import annotations

import dataclasses
from dataclasses import dataclass

from ebrl.config import ROLES, Config, ConfigError


@dataclass(frozen=True)
class HostPlan:
    roles: tuple[str, ...]  # services started on this host, in start order
    instance: int = 0  # this host's number in the run
    multi: bool = False  # one host of several: the launcher routes bus traffic between hosts
    name: str = ""  # the [hosts] entry, if any

    @property
    def primary(self) -> bool:
        return "train" in self.roles

    def instances(self, role: str, cfg: Config) -> range:
        """Instances of ``role`` started here: sim/<host> and alloc/<host>, train ranks 0..world_size-1, one of
        the others."""
        if role in ("sim", "alloc"):
            return range(self.instance, self.instance + 1)
        if role == "train":
            return range(cfg.train.world_size)
        return range(1)


def enabled_roles(cfg: Config) -> tuple[str, ...]:
    """Every service the run has, in start order: viz first (it sees the run from its start), the allocator
    last (it only reads the others' stats)."""
    return tuple(r for r in ROLES if (r != "viz" or cfg.viz.rerun != "off") and (r != "alloc" or cfg.alloc.enabled))


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
        # viz goes with train unless some host names it; the allocator always does (it plans that host's cores)
        wanted = set(entry.services) | ({"viz", "alloc"} - named if "train" in entry.services else set())
        _allocator_with_train(wanted, f"[hosts.{host}]")
        bus = dataclasses.replace(cfg.bus, listen=list(entry.listen or cfg.bus.listen),
                                  connect=list(entry.connect or cfg.bus.connect))
        sim = dataclasses.replace(cfg.sim, cores=list(entry.cores or cfg.sim.cores))
        cfg = dataclasses.replace(cfg, bus=bus, sim=sim)
        return cfg, HostPlan(tuple(r for r in every if r in wanted), list(cfg.hosts).index(host), True, host)
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
        raise ConfigError(f"--only {only}: {', '.join(missing)} is off in this config (viz.rerun / alloc.enabled)")
    number = 0 if instance is None else instance
    if number < 0:
        raise ConfigError(f"--instance {number}: must be >= 0")
    wanted = set(asked) | ({"alloc"} if "train" in asked else set())  # the allocator goes with training
    _allocator_with_train(wanted, f"--only {only}")
    return cfg, HostPlan(tuple(r for r in every if r in wanted), number, True)


def _allocator_with_train(roles: set[str], where: str) -> None:
    if "alloc" in roles and "train" not in roles:
        raise ConfigError(f"{where}: the allocator (alloc) runs on the host that trains: it plans that host's "
                          "cores, reading every host's stats")
