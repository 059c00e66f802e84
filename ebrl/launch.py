"""``ebrl up``: from the prepared run (``ebrl.prepare``: config, preflight, "auto", allocation, run directory),
spawn every service as its own process, supervise, report, shut down.

The launcher is a bus peer like the services: it listens on ``bus.listen``
(services and scripts connect there), watches liveliness tokens to know who is
up, reads ``ebrl/stats/<run>/**`` for the progress line, and stops the run with
``ctl/.../stop`` messages, then SIGTERM, then SIGKILL, so that no process is
left after ``ebrl.supervisor.SHUTDOWN_S`` seconds. :class:`Launcher` wires its
parts to the bus: the processes (``ebrl.supervisor``), the run as the stats
show it (``ebrl.runview``) and the liveliness tokens (``ebrl.hosts.Membership``).
The allocator tells it when a stage needs a new GPU share (``GpuShare`` on
``ctl/<run>/launcher/<host>/gpu_share``): it restarts that stage with it.

In a run over several hosts (``--only``, ``--host``: ``ebrl.hosts``) there is
one launcher per host, started the same way. Each is then a Zenoh *router*: the
services of its host still talk to each other directly, and what crosses hosts
is routed between the launchers. The primary (the host with ``train``) reports
hosts joining and leaving and ends the run for everyone (``ctl/<run>/launcher/
all/stop``); a host whose primary is gone for ``PRIMARY_LOST_S`` stops too.
"""

from __future__ import annotations

import asyncio
import collections
import functools
import json
import logging
import signal
import sys
import time
from pathlib import Path
from typing import Callable

from ebrl import config as config_mod, durable, prepare, procenv, stall
from ebrl import graph, keys
from ebrl.bus import auth
from ebrl.bus.session import Bus, BusOptions
from ebrl.bus.endpoints import (address_in_use, config_file_connect, config_file_listen, free_port,
                                listen_endpoint)
from ebrl.bus.joincheck import await_link, diagnose
from ebrl.bus.zlog import ZenohLog
from ebrl.hosts import PRIMARY_LOST_S, HostPlan, Membership, enabled_roles, planned_instances, sim_hosts
from ebrl.messages import Event, GpuShare, StatsReport, Stop
from ebrl.ranknet import across_hosts
from ebrl.weights import known_version
from ebrl.runview import Console, RunView, summary as run_summary, warm_report, write_report, write_summary
from ebrl.sched.modes import resolve
from ebrl.service import STOP_TO_RESTART, bus_metrics, control_version_refused
from ebrl.supervisor import Argv, RestartPolicy, Supervisor, not_up
from ebrl.viz import record, web_url

log = logging.getLogger("ebrl.launch")

EVERY_HOST = "all"  # the instance chunk of the run-wide stop: ctl/<run>/launcher/all/stop
PRIMARY_ENDED = "the primary host ended the run"
OPTIONAL_ROLES = tuple(name for name, role in graph.ROLES.items() if role.optional)  # ebrl.graph.Role.optional


def service_argv(config_path: Path, endpoint: str) -> Argv:
    """``python -m <the role's module> --config ... --instance N [--connect <the launcher's endpoint>]``."""
    def argv(role: str, instance: int) -> list[str]:
        module = graph.ROLES[role].module  # ebrl.services.<role>
        cmd = [sys.executable, "-m", module, "--config", str(config_path), "--instance", str(instance)]
        return cmd + (["--connect", endpoint] if endpoint else [])
    return argv


def process_argv(config_path: Path, endpoint: str) -> Callable[[tuple[tuple[str, int], ...]], list[str]]:
    """``python -m ebrl.process --config ... --service ROLE/N ... [--connect ...]``: services sharing a process."""
    def argv(services: tuple[tuple[str, int], ...]) -> list[str]:
        cmd = [sys.executable, "-m", "ebrl.process", "--config", str(config_path)]
        cmd += [arg for role, n in services for arg in ("--service", f"{role}/{n}")]
        return cmd + (["--connect", endpoint] if endpoint else [])
    return argv


def role_env(cfg: config_mod.Config, plan: HostPlan) -> dict[str, dict[str, str]]:
    """The EBRL variables of each role's processes (``ebrl.procenv``): the allocator, whether this host
    simulates (it plans this host); generation and the simulators, the run's simulator hosts (what they count as
    serving: ``ebrl.hosts.sim_hosts``)."""
    env = {"alloc": procenv.service_env(local_sim="sim" in plan.roles)}
    hosts = sim_hosts(cfg, plan)
    if hosts is not None:
        env.update({role: procenv.service_env(sim_hosts=hosts) for role in ("gen", "sim")})
    return env


def instance_env(cfg: config_mod.Config, run_dir: Path) -> Callable[[str, int], dict[str, str]] | None:
    """Each process's own bus identity (``ebrl.bus.auth.instance_line``), where the launcher's router admits
    identities per instance (``bus.mode = "client"`` with ``bus.auth``); None elsewhere (a mesh signs in by
    role)."""
    secret = auth.secret_path(cfg.bus, run_dir)
    if not secret or cfg.bus.mode != "client":
        return None
    return lambda role, instance: procenv.service_env(identity=auth.instance_line(secret, role, instance))


def banner(cfg: config_mod.Config, plan: HostPlan, run_dir: Path, endpoint: str) -> str:
    where = f"host {plan.name or plan.instance}: {', '.join(plan.roles)}; " if plan.multi else ""
    return f"run {cfg.run.name}: {run_dir}  ({where}bus {endpoint or ', '.join(cfg.bus.connect)})"


def launcher_endpoint(cfg: config_mod.Config, plan: HostPlan) -> str:
    """Where this host's launcher listens: the first of bus.listen (or of bus.config_file's, which are kept), a
    free port if it is taken, unless other hosts connect there (:func:`fixed_listen`); empty when it only
    connects."""
    listen = config_file_listen(cfg.bus.config_file) or cfg.bus.listen
    return listen_endpoint(listen[0], strict=fixed_listen(cfg, plan)) if listen else ""


def fixed_listen(cfg: config_mod.Config, plan: HostPlan) -> bool:
    """Whether this host's listen endpoint must be the one configured: bus.config_file names it, or other hosts
    connect to it (a host of several that connects to none itself: the primary, say). A host that connects to
    another is reached only by its own services: a second launcher on one machine takes a free port."""
    connects = bool(cfg.bus.connect or config_file_connect(cfg.bus.config_file))
    return bool(config_file_listen(cfg.bus.config_file)) or (plan.multi and not connects)


def viz_line(viz: config_mod.VizSection, run_dir: Path) -> str:
    where = {"serve": f" (viewer: rerun --connect rerun+http://127.0.0.1:{viz.port}/proxy)",
             "web": f" (browser: {web_url(viz.port, viz.web_port)}; from a laptop: ssh -L {viz.web_port}:127.0.0.1:"
                    f"{viz.web_port} -L {viz.port}:127.0.0.1:{viz.port} HOST)"}
    return f"viz: rerun {viz.rerun} -> {run_dir / 'timeline.rrd'}" + where.get(viz.rerun, "")


def local_endpoint(endpoint: str) -> str:
    """Where this host's services and scripts reach its launcher: ``endpoint`` where it stays on this host, else
    a loopback TCP port of its own, so that they never go through TLS or another interface."""
    return endpoint if not endpoint or auth.is_loopback(endpoint) else f"tcp/127.0.0.1:{free_port()}"


def stopped_code(stop_reason: str) -> int:
    """The exit code of a run stopped from outside: 130 after SIGINT, 143 after SIGTERM, 0 where the primary
    host ended the run."""
    if stop_reason == PRIMARY_ENDED:
        return 0
    return 130 if stop_reason.startswith("signal SIGINT") else 143


class LauncherBus:
    """This host's launcher on the bus (a router when the run spans hosts): where it listens (``bus.json``), the
    recording of the run's stats, and what it publishes: events, its stats report, stops."""

    def __init__(self, cfg: config_mod.Config, plan: HostPlan, endpoint: str, run_dir: Path):
        self.run, self.host = cfg.run.name, plan.instance  # its stats and events are launcher/<host>
        self.keys = graph.keys_of(self.run, "launcher", self.host)
        listen = [endpoint, *cfg.bus.listen[1:]] if endpoint else []
        self.local = local_endpoint(endpoint)
        secret = auth.secret_path(cfg.bus, run_dir)
        # the router of this host's services when they are its clients (each signed in as its own instance and
        # checked against that instance's rights, ebrl.bus.auth), and between hosts
        instances, dictionary, groups = (), "", 0
        # every instance of the run, where this router passes on only their tokens (the launcher counts others)
        self.planned: tuple[tuple[str, int], ...] | None = None
        shares: tuple[tuple[tuple[str, int], ...], ...] = ()
        if secret and cfg.bus.mode == "client":
            processes = plan.processes(cfg)  # the first service of each signs in for it
            instances, self.planned = tuple(unit[0] for unit in processes), planned_instances(cfg, plan)
            shares = tuple(unit for unit in processes if len(unit) > 1)
            dictionary = str(auth.write_router_dictionary(
                secret, run_dir / auth.ROUTER_FILE.format(host=plan.instance), instances))
            groups = resolve(cfg).groups  # a simulator's groups: sim/n has n*groups .. (ebrl.sched.fleet)
        self.bus = Bus(BusOptions(mode="router" if plan.multi or cfg.bus.mode == "client" else "peer",
                                  listen=listen, connect=list(cfg.bus.connect), config_file=cfg.bus.config_file,
                                  secret_file=secret, file_listen_wins=True, local=self.local, role="launcher",
                                  run=self.run, host=plan.instance, instances=instances, dictionary_file=dictionary,
                                  groups=groups, planned=self.planned, shares=shares))
        mine = [self.local, *(e for e in listen if e != self.local)] if endpoint else []  # scripts take the first
        durable.write_text(run_dir / "bus.json", json.dumps({"listen": mine, "run": self.run}) + "\n")
        # the primary records the run; another host's launcher would draw every span across the link for a copy
        self.recorder = record.Recorder(run_dir / record.FILENAME) if cfg.viz.record and plan.primary else None
        if self.recorder is not None:
            self.bus.subscribe_raw(self.keys.sub("stats"), self.recorder.write)
        self._seq = 0
        self.ctl_unknown = 0  # control messages for a service this run does not have
        # control messages refused (refuse): GPU shares in a run without the allocator, or numbered far ahead
        self.refused = collections.Counter({"launcher/gpu_shares_refused": 0, "ctl/version_refused": 0})

    def count_unknown_controls(self, roles: tuple[str, ...] | list[str]) -> None:
        """Count control messages for a service this run does not have (every service ignores them)."""
        def on_control(key: str, payload: bytes) -> None:  # a Zenoh thread
            role = keys.role_of(key)
            if role != "launcher" and role not in roles:
                if not self.ctl_unknown:
                    log.warning("control message for an unknown service ignored: %s (further ones only counted)",
                                key)
                self.ctl_unknown += 1
        self.bus.subscribe_raw(self.keys.sub("ctl"), on_control)

    def refuse(self, counter: str, line: str, say: Callable[[str], None]) -> None:
        """Count a control message refused in ``refused[counter]`` (reported under that name); say ``line`` once."""
        if not self.refused[counter]:
            say(f"\nebrl: {line} (further ones only counted: {counter})")
        self.refused[counter] += 1

    def consume(self, key: str, cls: type, handler, capacity: int) -> asyncio.Task:
        """Call ``handler(key, message)`` on the event loop for each message on ``key`` (the latest
        ``capacity`` ones are kept while it is busy)."""
        async def consume(sub) -> None:
            async for at, msg in sub:
                handler(at, msg)
        return asyncio.create_task(consume(self.bus.subscribe(key, cls, policy="latest", capacity=capacity)))

    def event(self, kind: str, text: str) -> None:
        self.bus.put_nowait(self.keys.put("events"),
                            Event(time=time.time(), service="launcher", instance=self.host, kind=kind, text=text))

    def publish_stats(self, metrics: dict[str, float]) -> None:
        """``metrics`` with what the bus dropped (``bus/*``) and the control messages refused, as its report."""
        metrics = {**metrics, **bus_metrics(self.bus), **{name: float(n) for name, n in self.refused.items()}}
        self.bus.put_nowait(self.keys.put("stats"), StatsReport(
            run=self.run, service="launcher", instance=self.host, time=time.time(), seq=self._seq, metrics=metrics))
        self._seq += 1

    async def stop(self, role: str, instance: int | str, reason: str) -> None:
        await self.bus.put(self.keys.put("stop", service=role, instance=instance), Stop(reason=reason))

    async def stop_all(self, services: tuple[tuple[str, int], ...], reason: str) -> None:
        """Ask each of ``services`` (a process's) to stop."""
        for role, instance in services:
            await self.stop(role, instance, reason)

    async def close(self) -> None:
        await self.bus.close()
        if self.recorder is not None:
            self.recorder.close()


class FinalEvaluation:
    """Once run.iterations are done, the launcher waits for the eval service's result of the final version, at
    most ``timeout`` seconds (the other services idle meanwhile: no new version comes); not for a dead eval
    service, nor one on another host."""

    def __init__(self, timeout: float, final: int, say: Callable[[str], None]):
        self.timeout, self.final, self.say = timeout, final, say
        self.deadline: float | None = None  # monotonic

    def pending(self, view: RunView, children: list) -> bool:
        if (not any(c.has("eval") and not c.given_up for c in children) or self.timeout <= 0
                or (view.evaluated_version() or 0) >= self.final):
            return False
        now = time.monotonic()
        if self.deadline is None:
            self.deadline = now + self.timeout
            self.say(f"\nrun.iterations done: waiting for the evaluation of the final policy v{self.final} (at most "
                     f"eval.final_timeout = {self.timeout:g} s; Ctrl-C skips it)")
        if now > self.deadline:
            self.say(f"\nebrl: no evaluation of v{self.final} after {self.timeout:g} s; stopping without it")
            return False
        return True


def run_instances(cfg: config_mod.Config, plan: HostPlan, members: Membership) -> Callable[[str, int], bool]:
    """Whether the run has service instance ``role/instance``: a train rank, the one instance of the others, or
    a simulator or allocator of a host that is live (this one's, or another host's): a simulator of a host the
    run plans one on (:func:`ebrl.hosts.sim_hosts`; with hosts that join by ``--only``, one whose launcher is up),
    so that a token of another instance does not make its reports count."""
    hosts = sim_hosts(cfg, plan)

    def has(role: str, instance: int) -> bool:
        if role == "train":
            return 0 <= instance < cfg.train.world_size
        if role == "sim" and instance != plan.instance:
            planned = members.is_live("launcher", instance) if hosts is None else instance in hosts
            return planned and members.is_live(role, instance)
        if role in ("sim", "alloc", "launcher"):
            return instance == plan.instance or members.is_live(role, instance)
        return instance == 0

    return has


def open_launcher_bus(cfg: config_mod.Config, plan: HostPlan, run_dir: Path,
                      tries: int = 5) -> tuple[LauncherBus, str]:
    """This host's launcher on the bus and the endpoint it listens on. Between the check that a port is free
    (:func:`launcher_endpoint`) and Zenoh's bind, another process may take it (two runs started at the same
    moment): the bind is tried again on a free port, up to ``tries`` binds in all. OSError, with the reason,
    where it cannot: the port is fixed (other hosts connect to it, or bus.config_file names it) or no bind took."""
    endpoint = launcher_endpoint(cfg, plan)
    fixed = fixed_listen(cfg, plan)
    attempt = 1
    while True:
        try:
            return LauncherBus(cfg, plan, endpoint, run_dir), endpoint
        except Exception as exc:  # zenoh.ZError where its bind failed
            if not address_in_use(exc):
                raise
            if fixed or attempt >= tries:
                raise OSError(f"cannot listen on {endpoint}: the port is busy (another run?)") from None
            attempt += 1
            endpoint = listen_endpoint(endpoint)  # taken now: the same host on a free port


async def join_problem(cfg: config_mod.Config, plan: HostPlan, run_dir: Path, bus: Bus, stopping: asyncio.Event,
                       say: Callable[[str], None]) -> str | None:
    """The line to stop with where a host that connects to another (its learner's listen endpoint, an ``ebrl
    router``) has no link to it, with the cause (``ebrl.bus.joincheck``); None once it has one, or where it
    connects nowhere."""
    endpoints = [*cfg.bus.connect, *config_file_connect(cfg.bus.config_file)] if plan.multi else []
    if not endpoints:
        return None
    secret = auth.secret_path(cfg.bus, run_dir)
    problem = await await_link(lambda: bus.routers_linked() > 0 or stopping.is_set(), endpoints,
                               lambda endpoint: diagnose(endpoint, cfg.bus.config_file, secret, cfg.run.name),
                               lambda line: say(f"ebrl: {line}"), cfg.run.startup_timeout)
    return problem and f"ebrl: host {plan.name or plan.instance} cannot join run {cfg.run.name}: {problem}"


def apply_gpu_share(share: GpuShare, gpu_env: dict[str, dict[str, str]], supervisor: Supervisor, link: LauncherBus,
                    say: Callable[[str], None]) -> None:
    """A new GPU share for a stage of this host: its processes stop at their safe point (generation between
    batches, training after its update, its state in a checkpoint) and start again with it. Only the allocator
    makes shares, only on a GPU: one is refused (counted, said once) in a run that started without (no allocator,
    or no GPU), or numbered over ``ebrl.service.CONTROL_STEP`` past the stage's last (``ctl/version_refused``)."""
    if not gpu_env:
        link.refuse("launcher/gpu_shares_refused", f"a GPU share for {share.stage} refused: this run has no "
                    "GPU shares (no allocator on a GPU)", say)
        return
    if refused := control_version_refused(share.version, supervisor.share_versions.get(share.stage, 0)):
        link.refuse("ctl/version_refused", f"a GPU share for {share.stage} refused: {refused}", say)
        return
    for child in supervisor.new_gpu_share(share.stage, share.env, share.version):
        for instance in (n for role, n in child.services if role == share.stage):  # a process of several stops
            link.bus.put_nowait(link.keys.put("stop", service=share.stage, instance=instance),
                                Stop(reason=STOP_TO_RESTART))


class Launcher:
    def __init__(self, cfg: config_mod.Config, run_dir: Path, out=sys.stdout, plan: HostPlan | None = None,
                 gpu_env: dict[str, dict[str, str]] | None = None, notes: list[tuple[str, str]] | None = None,
                 zlog: ZenohLog | None = None):
        self.cfg, self.run_dir, self.run_name = cfg, run_dir, cfg.run.name
        self.notes = notes or []  # (kind, text): start-up events (what "auto" became), sent once services are live
        self.plan = plan or HostPlan(enabled_roles(cfg))
        self.roles = enabled_roles(cfg)  # every service of the run, on any host
        self.console = Console(out)
        self.members = Membership(cfg.run.name, self.plan.instance, self.plan.multi)
        self.view = RunView(cfg.run.name, cfg.run.iterations, cfg.run.target_return,
                            instances=run_instances(cfg, self.plan, self.members),
                            floor=known_version(str(run_dir)),  # a resumed run's checkpoint
                            target_success=cfg.run.target_success, max_abs_reward=cfg.env.max_abs_reward)
        self.gpu_env = gpu_env or {}  # stage -> the CUDA variables it starts with (the allocator's first GPU share)
        self.failure: str | None = None
        self.stop_reason = ""
        # the groups of each sim instance name the one whose segments stopped (ebrl.sched.fleet: sim/<n>'s groups)
        self.stalls = stall.StallWatch(cfg.run.stall_timeout, groups_per_sim=resolve(cfg).groups)
        self.started = time.monotonic()
        self.final_eval = FinalEvaluation(cfg.eval.final_timeout, cfg.run.iterations, self.console.say)
        self.zlog = zlog or ZenohLog()  # started by launch() on a host of several, else never started

    async def main(self) -> int:
        self.stopping = asyncio.Event()
        loop = asyncio.get_running_loop()
        for sig in (signal.SIGINT, signal.SIGTERM):
            loop.add_signal_handler(sig, self._on_signal, sig)
        try:
            self.link, endpoint = open_launcher_bus(self.cfg, self.plan, self.run_dir)
        except OSError as exc:
            self.console.say(f"ebrl: {exc}")
            return 2
        self.console.say(banner(self.cfg, self.plan, self.run_dir, endpoint))
        # Zenoh's account of the hosts it refuses, said here (ebrl.bus.zlog)
        self.zlog.on_refusal = lambda line: loop.call_soon_threadsafe(self.on_refused_host, line)
        if problem := await join_problem(self.cfg, self.plan, self.run_dir, self.link.bus, self.stopping,
                                         self.console.say):
            self.console.say(problem)
            await self.link.close()
            return 2
        if self.link.planned is not None:
            self.members.admit_only(self.link.planned)
        self.supervisor = Supervisor(
            service_argv(self.run_dir / "config.toml", self.link.local), self.run_dir / "logs",
            RestartPolicy(self.cfg.run.restart == "on-failure", self.cfg.run.max_restarts),
            say=self.console.say, event=self.link.event, gpu_env=self.gpu_env, train_ranks=self.cfg.train.world_size,
            role_env=role_env(self.cfg, self.plan), instance_env=instance_env(self.cfg, self.run_dir),
            version_floor=self.view.version_floor, optional=OPTIONAL_ROLES, across_hosts=across_hosts(self.cfg, self.plan),
            process_argv=process_argv(self.run_dir / "config.toml", self.link.local))
        self.link.bus.watch_liveliness(self.link.keys.watch(), functools.partial(follow_liveliness, self))
        self.link.count_unknown_controls(self.roles)
        if self.plan.multi and await self.members.number_taken():
            self.console.say(f"ebrl: host {self.plan.instance} of run {self.run_name} is already up elsewhere on the "
                             "bus; give each host its own --instance (or --host)")
            await self.link.close()
            return 2
        self.link.bus.declare_token(self.link.keys.token())
        stats_tasks = [self.link.consume(graph.keys_of(self.run_name, role, "*").put("stats"), StatsReport,
                                         self.view.on_report, 64) for role in self.roles]
        control_tasks = [self.link.consume(self.link.keys.sub("gpu_share"), GpuShare,
                                           self.on_gpu_share, 16)]
        if self.plan.multi and not self.plan.primary:
            control_tasks.append(self.link.consume(self.link.keys.sub("stop"), Stop,
                                                   self.on_primary_ended, 4))
        code = 1
        try:
            for services in self.plan.processes(self.cfg):
                self.supervisor.start(*services[0], members=services)
            if await self.wait_live():
                code = await self.supervise()
            elif self.stopping.is_set() and self.failure is None:  # Ctrl-C (or SIGTERM) while starting
                code = stopped_code(self.stop_reason)
        finally:
            for task in control_tasks:  # no new GPU share while stopping
                task.cancel()
            await self.stop_services()
            for task in stats_tasks:
                task.cancel()
            await self.link.close()
        self.finish(code)
        return code

    def elapsed(self) -> float:
        return time.monotonic() - self.started

    async def wait_live(self) -> bool:
        """Wait for every service the run needs. An optional one (log, eval) is not waited for: at idle priority
        on a busy machine, eval can take minutes to start, and nothing waits on it; it joins when it is up."""
        children = [c for c in self.supervisor.children if not all(r in OPTIONAL_ROLES for r, _ in c.services)]
        deadline = time.monotonic() + self.cfg.run.startup_timeout
        while missing := [c for c in children if not c.given_up
                          and not all(self.members.is_live(role, n) for role, n in c.services)]:
            if self.stopping.is_set():
                return False
            self.failure = self.supervisor.check(restart=False)
            if self.failure is not None:
                return False
            if time.monotonic() > deadline:
                self.failure = not_up(missing, self.cfg.run.startup_timeout, self.console.say)
                return False
            await asyncio.sleep(0.05)
        names = ", ".join(c.name for c in children)
        self.console.say(f"all services live after {self.elapsed():.1f} s: {names}")
        self.link.event("live", f"{names} live after {self.elapsed():.1f} s")
        for kind, text in self.notes:
            self.link.event(kind, text)
        if later := [c.name for c in self.supervisor.children if all(r in OPTIONAL_ROLES for r, _ in c.services)
                     and not self.members.is_live(c.role, c.instance)]:
            self.console.say(f"{', '.join(later)} still starting (optional: the run does not wait for it)")
        if self.cfg.viz.rerun != "off":
            self.console.say(viz_line(self.cfg.viz, self.run_dir))
        return True

    async def supervise(self) -> int:
        last_stats = 0.0
        while not self.stopping.is_set():
            self.failure = self.supervisor.check(restart=True) or stall.watch(
                self.stalls, self.view, self.supervisor, self.console.say, self.link.event) or ranks_lost(self)
            if self.failure is not None:
                return 1
            if time.monotonic() - last_stats >= self.cfg.run.stats_interval:
                self.publish_stats()
                last_stats = time.monotonic()
            self.show_progress()
            if not self.plan.primary:
                if self.members.primary_lost():
                    self.failure = f"no train on the bus for {PRIMARY_LOST_S:.0f} s: the primary host is gone"
                    self.console.say(f"\nebrl: {self.failure}")
                    return 1
            elif self.view.iterations_done():
                if not self.final_eval.pending(self.view, self.supervisor.children):
                    self.show_progress(force=True)
                    return 0
            elif (reached := self.view.target_reached(self.elapsed())) is not None:
                self.show_progress(force=True)
                self.console.say(reached)
                return 0
            try:
                await asyncio.wait_for(self.stopping.wait(), 0.5)
            except asyncio.TimeoutError:
                pass
        return stopped_code(self.stop_reason)

    def show_progress(self, force: bool = False) -> None:
        hosts = len(self.members.hosts_up) + 1 if self.plan.multi else None
        restarts = sum(self.supervisor.restarts().values())
        self.console.progress(self.view.progress(self.elapsed(), restarts, hosts), force)

    def publish_stats(self) -> None:
        """The launcher's own stats report: restarts per service, services up."""
        metrics = {**self.supervisor.metrics(), "launcher/ctl_unknown_service": float(self.link.ctl_unknown),
                   "launcher/services_live": float(self.members.services_live()),
                   "launcher/unknown_instances": float(self.members.unknown_seen),
                   "launcher/stats_refused": float(self.view.refused),
                   "launcher/hosts_refused": float(self.zlog.refused),
                   "launcher/returns_refused": float(self.view.returns_refused)}
        self.link.publish_stats(metrics)

    async def stop_services(self) -> None:
        self.members.ending = True
        if self.cfg.viz.report:
            warm_report()  # its imports while the services stop
        self.link.event("stopping", self.failure or self.stop_reason or "run finished")
        if self.plan.multi and self.plan.primary:  # every host ends with the primary
            await self.link.stop("launcher", EVERY_HOST, self.failure or self.stop_reason or "run finished")
        self.console.end_progress()
        await self.supervisor.shutdown(lambda child: self.link.stop_all(child.services, self.stop_reason or "run finished"))

    def finish(self, code: int) -> None:
        """summary.json, its line, and the headless report."""
        summary = run_summary(self.view, code, self.elapsed(), run_dir=self.run_dir, failure=self.failure,
                              restarts=self.supervisor.restarts(), host=self.plan.instance,
                              hosts=self.members.hosts())
        self.console.say(write_summary(summary, self.run_dir / "summary.json"))
        if self.cfg.viz.report and self.link.recorder is not None and self.link.recorder.samples:
            self.console.say(write_report(self.run_dir))

    # --- bus events ---------------------------------------------------------------

    def on_gpu_share(self, key: str, share: GpuShare) -> None:
        apply_gpu_share(share, self.gpu_env, self.supervisor, self.link, self.console.say)

    def on_refused_host(self, line: str) -> None:
        """Zenoh refused a host's link (``ebrl.bus.zlog``): said, and an event of the run."""
        self.console.say(f"\nebrl: {line}")
        self.link.event("refused", line)

    def on_primary_ended(self, key: str, stop: Stop) -> None:
        self.stop(PRIMARY_ENDED, f"\nebrl: {PRIMARY_ENDED}; stopping this host's services")

    def stop(self, reason: str, line: str) -> None:
        if not self.stopping.is_set():
            self.stop_reason = reason
            self.console.say(line)
            self.stopping.set()

    def _on_signal(self, sig: signal.Signals) -> None:
        self.stop(f"signal {sig.name}", f"\nebrl: {sig.name} received, stopping every service")


def ranks_lost(launcher: Launcher) -> str | None:
    """Where training ranks run on several hosts: the failure once a rank of another host left (the group cannot
    go on without it, and is not restarted across hosts), said; else None."""
    plan, cfg = launcher.plan, launcher.cfg
    if not (plan.ranks_elsewhere and "train" in plan.roles):
        return None
    mine = plan.ranks or range(0)
    gone = [n for n in launcher.members.gone("train", range(cfg.train.world_size)) if n not in mine]
    if not gone:
        return None
    failure = (f"training rank{'s' * (len(gone) > 1)} {', '.join(f'train/{n}' for n in gone)} of another host left "
               "the run: the group cannot go on without it and is not restarted across hosts (ebrl up --resume "
               "RUN_DIR on the primary goes on from its latest checkpoint)")
    launcher.console.say(f"\nebrl: {failure}")
    launcher.link.event("exited", failure)
    return failure


def follow_liveliness(launcher: Launcher, key: str, alive: bool) -> None:
    """A token of the run appeared or vanished: the launcher's membership follows it (and its view: the rates of
    an instance that left count no more); another host joining or leaving, and the first token of an instance
    the run does not have (every one counted: ``launcher/unknown_instances``), are said and recorded as events."""
    members, console, link, view = launcher.members, launcher.console, launcher.link, launcher.view
    unknown = members.unknown_seen
    change = members.update(key, alive)
    if not alive:
        try:
            parsed = keys.parse(key)
        except ValueError:  # not a process's token
            parsed = None
        if parsed is not None:
            view.left(parsed.service, parsed.instance)
    if members.unknown_seen and not unknown:
        what = (f"a liveliness token of an instance this run does not have ({key}) reached this host's router; "
                "it stops there, counted in launcher/unknown_instances")
        console.say(f"\nebrl: {what}")
        link.event("unknown_instance", what)
    if change is None:
        return
    what = f"host {change.host} {'joined' if change.joined else 'left'} the run"
    console.say(f"\nebrl: {what}" + ("" if change.joined else "; nothing waits for its groups"))
    link.event("host", what)


def up(config_path: str, overrides: list[str], viz: str | None = None, resume: str | None = None,
       only: str | None = None, host: str | None = None, instance: int | None = None) -> int:
    """``ebrl up``: exit 2 where the run cannot start (a config error, a failed preflight: nothing started),
    else the run's exit code. The options are :func:`ebrl.prepare.prepare`'s."""
    try:
        run = prepare.prepare(config_path, overrides, viz=viz, resume=resume, only=only, host=host,
                              instance=instance)
    except prepare.NotStarted as exc:
        print(f"ebrl: {exc}", file=sys.stderr)
        return 2
    return launch(run)


def launch(run: prepare.PreparedRun, out=None) -> int:
    """Start a prepared run's services on this host and supervise them until the run ends; its exit code
    (130 after Ctrl-C, which stops every service first). On a host of several, Zenoh's log of the links it
    refuses is read first (``ebrl.bus.zlog``: ``sys.stdout`` is a new object after it)."""
    logging.basicConfig(level=logging.WARNING, format="%(levelname)s %(name)s: %(message)s")
    zlog = ZenohLog()
    if run.plan.multi:
        zlog.start()
    try:
        return asyncio.run(Launcher(run.cfg, run.run_dir, out=out or sys.stdout, plan=run.plan, gpu_env=run.gpu_env,
                                    notes=run.notes, zlog=zlog).main())
    finally:
        zlog.stop()
        run.close()
