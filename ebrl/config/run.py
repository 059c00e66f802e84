"""The run's own sections: ``[run]`` (name, iterations, targets, restarts, process placement), ``[bus]`` and
``[hosts.<name>]``."""

from __future__ import annotations

from dataclasses import dataclass
from typing import Literal

from ebrl import graph
from ebrl import keys
from ebrl.config.base import ConfigError, doc, Section, parse_slowdown


@dataclass
class RunSection(Section):
    NAME = "run"
    POSITIVE = ("stats_interval",)

    name: str = doc("run name; part of every bus key, so two runs never see each other", "quickstart")
    mode: Literal["ebrl", "colocated", "hybrid", "async"] = doc(
        "ebrl: every mechanism; colocated: all envs step together, then train; hybrid: sim/gen pipelined "
        "across groups, barrier before training; async: rollout and training overlap on disjoint cores, "
        "batch-synchronous stepping", "ebrl")
    iterations: int = doc("training updates (policy versions) after which the run ends; 0 runs until Ctrl-C", 100)
    target_return: float | None = doc(
        "end the run early once the mean return of the last 20 episodes training took (train/episode_return_mean, "
        "as training reports it) reaches this; absent: never", None)
    target_success: float | None = doc(
        "end the run early once the success rate of the last 20 episodes training took (train/success_rate, tasks "
        "that report success) reaches this fraction (0.9: 90 %); absent: never", None)
    seed: int = doc("seed for environments and model initialisation", 0)
    output_dir: str = doc("where run directories (logs, resolved config, summary) are created", "runs")
    group: str = doc("a Unix group whose members may read the run's directory (mode 0750, that group); empty: "
                     "only you (mode 0700: the logs, config, stats and policy of a run are its owner's)", "")
    stall_timeout: float = doc(
        "seconds a stage may stop moving (a service's stats reports, env steps, answered observations, updates) "
        "before the launcher says which and why, restarts it, and ends the run if that does not help "
        "(ebrl/stall.py); each stage is watched from its first progress on; 0: off", 30.0)
    stats_interval: float = doc("seconds between stats reports of each service", 1.0)
    startup_timeout: float = doc("seconds to wait for every service to come up", 120.0)
    log_level: Literal["debug", "info", "warning"] = doc("log level of the services", "info")
    slowdown: str = doc("inject a slowdown for experiments: \"<service>=<factor>@<seconds>\" stretches every busy "
                        "span of that service by factor (CPU busy-wait) from that many seconds after it started, "
                        "e.g. \"train=1.3@30\"; empty: none", "")
    restart: Literal["on-failure", "never"] = doc(
        "a service that dies is started again (on-failure, with backoff, at most max_restarts times per service) "
        "or the run stops (never)", "on-failure")
    max_restarts: int = doc("most restarts of one service before the run stops", 3)
    processes: list[list[str]] | Literal["auto"] = doc(
        "services that share one process on their host, e.g. [[\"sim\", \"gen\", \"train\"]]: the messages between "
        "them never leave it (one bus session, no router hop, no socket), each keeps its own stats, lanes, token "
        "and rights, and a process that dies is started again with every service in it. A simulator that shares "
        "a process shares its memory: the env's code can then reach the others (docs/processes.md). Empty: each "
        "service in a process of its own. \"auto\": sim, gen and train in one process on a host with a GPU that "
        "runs all three (one training rank, no allocator) with a GPU simulator EBRL ships (env.backend = \"mjwarp\", "
        "its own task); on a CPU host, sim and gen in one process where the run is the ebrl mode without the "
        "allocator, each env a worker process of its own (not sim.vectorized) and no module:EnvId of yours; else "
        "each alone; decided at start, written into the run's config.toml", "auto")

    def _check(self) -> None:
        try:
            keys.check_chunk(self.name, "run.name")
        except ValueError as exc:
            raise ConfigError(str(exc)) from None
        if self.target_success is not None and not 0.0 < self.target_success <= 1.0:
            raise ConfigError(f"run.target_success = {self.target_success}: a fraction in (0, 1] (0.9: 90 %)")
        if self.iterations < 0 or self.max_restarts < 0:
            raise ConfigError(f"run.iterations ({self.iterations}) and run.max_restarts ({self.max_restarts}) must "
                              "be >= 0")
        seen: set[str] = set()
        for group in [] if self.processes == "auto" else self.processes:
            if len(group) < 2:
                raise ConfigError(f"run.processes: {group}: a shared process holds at least two services")
            for role in group:
                if role not in ROLES:
                    raise ConfigError(f"run.processes: unknown service {role!r}; services are {', '.join(ROLES)}")
                if role in seen:
                    raise ConfigError(f"run.processes: {role} is named twice; a service runs in one process")
                seen.add(role)
        if self.slowdown:
            try:
                parse_slowdown(self.slowdown)
            except ValueError as exc:
                raise ConfigError(f"run.slowdown = {self.slowdown!r}: {exc}") from None


@dataclass
class BusSection(Section):
    NAME = "bus"

    mode: Literal["peer", "client"] = doc(
        "how services meet: client (each a client of its host's launcher, which routes and, with bus.auth, takes "
        "from each only what its role may send: one identity per role) or peer (a mesh: services talk directly, "
        "a few percent faster on message-heavy runs, and trust each other's credentials; observers still only "
        "read)", "client")
    listen: list[str] = doc(
        "endpoints the launcher listens on; services and scripts connect here (a busy port falls back to a free one)",
        factory=lambda: ["tcp/127.0.0.1:7447"],
    )
    connect: list[str] = doc("extra endpoints to connect to (a Zenoh router or another host)", factory=list)
    config_file: str = doc("path to a native Zenoh JSON5 config (TLS, access control); empty for none", "")
    max_message_bytes: int = doc("a received message larger than this is dropped before it is decoded: by Zenoh "
                                 "(its receive limit) or counted as bus/oversized; each message type has its own "
                                 "lower limit too (schemas/: x-ebrl-max-bytes)", 256 << 20)
    auth: bool = doc("every process of the run signs in with the run's secret (RUN_DIR/bus.secret, 0600): a process "
                     "without it can neither join nor read the bus. false: an open bus that any process on the host "
                     "can join", True)
    secret_file: str = doc("the run's secret file; empty: RUN_DIR/bus.secret, created by the launcher. A run over "
                           "several hosts needs one shared file (create it with `ebrl secret PATH`, copy it to each "
                           "host)", "")
    insecure: bool = doc("allow plain (unencrypted) endpoints that leave this host in bus.listen / bus.connect; "
                         "without it such an endpoint is refused: use tls/... with bus.config_file", False)

    def _check(self) -> None:
        if not self.listen and not self.connect:
            raise ConfigError("bus.listen and bus.connect are both empty: services could not find each other")


ROLES = graph.START_ORDER  # every service a host can run, in start order (ebrl.graph.Role.start)


@dataclass
class HostEntry:
    """One ``[hosts.<name>]`` table: what ``ebrl up CONFIG --host <name>`` starts on that machine."""

    services: list[str] = doc(f"services this host runs, from {', '.join(ROLES)}", factory=list)
    listen: list[str] = doc("bus endpoints this host's launcher listens on (reachable by the other hosts; under "
                            "srun, {primary} and {node} name the primary's node and this one: docs/scaling-out.md); "
                            "empty: bus.listen", factory=list)
    connect: list[str] = doc("bus endpoints this host's launcher connects to (another host's listen endpoint, or "
                             "an `ebrl router`); empty: bus.connect", factory=list)
    cores: list[int] = doc("sim.cores on this host; empty: the config's sim.cores", factory=list)
    ranks: int = doc("training ranks on this host, where it runs train and others do too (ranks are numbered "
                     "across hosts in [hosts] order); 0: an equal share of the train.world_size ranks the other "
                     "entries leave", 0)
