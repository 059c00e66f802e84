"""The service processes of one host: started, restarted after a failure or for a new GPU share, stopped in order.

A child is ``python -m ebrl.services.<role>`` (or any command line: tests start small
Python scripts) in a process group of its own, so that Ctrl-C reaches only the
launcher, which stops the children in order; it dies with the launcher
(``PR_SET_PDEATHSIG``) and appends its output to ``logs/<role>-<instance>.log`` (a process of several services,
``run.processes``: ``logs/train-0+gen-0+sim-0.log``).
Whatever a child started in its group is killed as soon as the child is seen to
have exited (before it is started again, or given up; at shutdown), so no
orphaned grandchild of an old child outlives it.

A child that exits on its own is started again after a backoff (1, 2, 4 ... s)
at most ``run.max_restarts`` times when ``run.restart = "on-failure"``, then
reported as the run's failure; an *optional* child (the tracking sinks: no other
service needs it) is then given up and the run goes on without it. A child asked to stop for a new GPU share is
started again with it as soon as it has exited: a *requota*, counted apart (``launcher/requotas``), not as a
restart, and limited alike: a child is started again for a new share at most ``run.max_restarts`` times, then the
run ends. Shutdown: a ``Stop`` over the bus (the caller sends it), SIGTERM after
``STOP_GRACE_S``, SIGKILL to the process group at ``SHUTDOWN_S``.
"""

from __future__ import annotations

import asyncio
import contextlib
import ctypes
import dataclasses
import logging
import os
import secrets
import signal
import subprocess
import time
from pathlib import Path
from typing import Awaitable, Callable

from ebrl import procenv

log = logging.getLogger("ebrl.supervisor")

STOP_GRACE_S = 5.0  # after the stop message, before SIGTERM
SHUTDOWN_S = 8.0  # after which anything left is SIGKILLed
KILL_WAIT_S = 10.0  # for a SIGKILLed child to be gone (a process in uninterruptible I/O takes its time)
LOG_TAIL = 20

Argv = Callable[[str, int], list[str]]  # (role, instance) -> the command line of that child
ProcessArgv = Callable[[tuple[tuple[str, int], ...]], list[str]]  # the command line of a process of several


@dataclasses.dataclass
class Child:
    role: str
    instance: int
    proc: subprocess.Popen
    log_path: Path
    restarts: int = 0
    restart_at: float | None = None  # monotonic time of a scheduled restart
    requota: bool = False  # asked to stop for a new GPU share: started again with it once it has exited
    requotas: int = 0  # times it was started again with a new GPU share (launcher/requotas)
    given_up: bool = False  # an optional child that exited for good: the run goes on without it
    started: float = dataclasses.field(default_factory=time.monotonic)  # when its process was last started
    # the service instances of a process of several (run.processes), ``role/instance`` the first; empty: that one
    members: tuple[tuple[str, int], ...] = ()

    @property
    def services(self) -> tuple[tuple[str, int], ...]:
        """The service instances in this child's process."""
        return self.members or ((self.role, self.instance),)

    @property
    def names(self) -> list[str]:
        """``role/instance`` of each service in its process."""
        return [f"{role}/{instance}" for role, instance in self.services]

    @property
    def name(self) -> str:
        return "+".join(self.names)

    def has(self, role: str) -> bool:
        return any(r == role for r, _ in self.services)

    def running(self) -> bool:
        """Whether the child still runs. Once it has exited, its process group (whatever it started and left
        behind) is killed before the child is reaped: until then its pid, the group's id, cannot be reused."""
        if self.proc.returncode is not None:
            return False
        try:
            exited = os.waitid(os.P_PID, self.proc.pid, os.WEXITED | os.WNOHANG | os.WNOWAIT) is not None
        except ChildProcessError:  # reaped already
            exited = True
        if not exited:
            return True
        _kill_group(self)
        self.proc.wait()  # reaps it (it has exited: at once)
        return False

    def tail(self, n: int = LOG_TAIL) -> str:
        try:
            lines = self.log_path.read_text(errors="replace").splitlines()
        except OSError:
            return "(no log)"
        return "\n".join("    " + line for line in lines[-n:])


@dataclasses.dataclass(frozen=True)
class RestartPolicy:
    """``run.restart`` and ``run.max_restarts``: whether, how often and how soon a child that exited starts again."""

    on_failure: bool
    max_restarts: int
    first_delay_s: float = 1.0  # doubled at each restart of the same child, at most MAX_DELAY_S

    MAX_DELAY_S = 30.0

    def allows(self, restarts: int) -> bool:
        return self.on_failure and restarts < self.max_restarts

    def delay(self, restarts: int) -> float:
        return min(self.first_delay_s * 2.0 ** restarts, self.MAX_DELAY_S)


def requotas_spent(child: Child, limit: int, version: int, say: Callable[[str], None],
                   event: Callable[[str, str], None]) -> str:
    """The run's failure when a GPU share of ``version`` would start ``child`` again once more than ``limit``
    (``run.max_restarts``) times: requotas count against it per child, as restarts do, so a flood of shares
    cannot restart a stage forever. Said and recorded here."""
    failure = (f"{child.name} was started again for a new GPU share {child.requotas} times, as many as "
               f"run.max_restarts = {limit} allows; the share of version {version} is refused and the run ends (a "
               "run whose allocator re-plans often needs a larger run.max_restarts)")
    event("exited", failure)
    say(f"\nebrl: {failure}")
    return failure


def child_env(child: Child, gpu_env: dict[str, dict[str, str]], role_env: dict[str, dict[str, str]],
              identity_env: dict[str, str], dist_addr: str, train_ranks: int, interface: str = "lo") -> dict[str, str]:
    """The environment of ``child``'s process: each of its services' variables (those of several agree), the
    identity of the first (``identity_env``), which signs in for the process; training's rendezvous, and the
    network interface its ranks connect over (``interface``: loopback where they all run on this host)."""
    env = dict(os.environ, PYTHONUNBUFFERED="1")
    for role, _ in child.services:
        env.update(**gpu_env.get(role, {}), **role_env.get(role, {}))
    env.update(identity_env)
    if child.has("train"):
        env.update(procenv.service_env(dist_addr=dist_addr))
        if train_ranks > 1:  # gloo's and NCCL's connections between the ranks: on this host, or the trusted network
            env.setdefault("GLOO_SOCKET_IFNAME", interface)
            if interface != "lo":  # NCCL on one host needs no socket interface of ours
                env.setdefault("NCCL_SOCKET_IFNAME", interface)
    env["PYTHONPATH"] = str(Path(__file__).resolve().parent.parent) + os.pathsep + env.get("PYTHONPATH", "")
    return env


def not_up(missing: list[Child], after_s: float, say: Callable[[str], None]) -> str:
    """The failure of a start that timed out, said with the last lines of each missing child's log."""
    failure = f"not up after {after_s:.0f} s: " + ", ".join(sorted(c.name for c in missing))
    say("ebrl: " + failure)
    for child in missing:
        say(f"--- last lines of {child.log_path}:\n{child.tail()}")
    return failure


def _die_with_parent() -> None:  # runs in the child between fork and exec
    os.setpgrp()  # Ctrl-C reaches the launcher only; it stops the children in order
    libc = ctypes.CDLL("libc.so.6", use_errno=True)
    libc.prctl(1, signal.SIGTERM)  # PR_SET_PDEATHSIG: a killed launcher takes its children along


def _kill_group(child: Child) -> None:
    """SIGKILL ``child``'s process group (its id is the child's pid: ``_die_with_parent`` made it), which outlives
    the child while anything it started is in it; only while the child is unreaped (:meth:`Child.running`)."""
    with contextlib.suppress(ProcessLookupError, PermissionError):
        os.killpg(child.proc.pid, signal.SIGKILL)


class Supervisor:
    """The children of one host and what happens when one exits. ``say`` prints a line for the user, ``event``
    records one in the run's event log; ``version_floor`` is the newest policy version seen (a restarted train
    starts past it)."""

    def __init__(self, argv: Argv, log_dir: Path, policy: RestartPolicy, *,
                 say: Callable[[str], None], event: Callable[[str, str], None],
                 gpu_env: dict[str, dict[str, str]] | None = None, role_env: dict[str, dict[str, str]] | None = None,
                 train_ranks: int = 1, version_floor: Callable[[], int] = lambda: -1, optional: tuple[str, ...] = (),
                 instance_env: Callable[[str, int], dict[str, str]] | None = None,
                 process_argv: ProcessArgv | None = None, across_hosts: tuple[str, str] | None = None):
        self.argv, self.log_dir, self.policy = argv, log_dir, policy
        self.process_argv = process_argv  # for a child of several services (run.processes)
        self.say, self.event, self.version_floor = say, event, version_floor
        self.gpu_env = dict(gpu_env or {})  # stage -> the CUDA variables its processes start with (its GPU share)
        self.share_versions: dict[str, int] = {}  # stage -> version of its last GPU share
        self.role_env = dict(role_env or {})  # role -> EBRL variables of its processes (ebrl.procenv)
        # (role, instance) -> EBRL variables of that one process: its own bus identity (ebrl.bus.auth)
        self.instance_env = instance_env or (lambda role, instance: {})
        self.train_ranks = train_ranks
        self.optional = optional  # roles whose death never ends the run
        # training ranks on several hosts: (train.rendezvous, this host's interface in train.trusted_networks)
        self.across_hosts = across_hosts
        # the training ranks' rendezvous, new for each start of the group (across hosts: the one they agreed on)
        self.dist_addr = f"tcp://{across_hosts[0]}" if across_hosts else self.rendezvous() if train_ranks > 1 else ""
        self.children: list[Child] = []
        self.requota_failure: str | None = None  # the run's failure once a child used up its requotas

    def rendezvous(self) -> str:
        """Where the training ranks meet: a file store in the run's directory (its owner's alone, 0700), not a
        TCP store (torch's listens on every interface, with no secret); each start of the group a new one."""
        return f"file://{self.log_dir.parent.resolve()}/.dist-{secrets.token_hex(8)}"

    def start(self, role: str, instance: int, members: tuple[tuple[str, int], ...] = ()) -> Child:
        """Start service ``role/instance``, or a process of the services ``members`` (the first of which it is)."""
        stem = "+".join(f"{r}-{n}" for r, n in members) if len(members) > 1 else f"{role}-{instance}"
        log_path = self.log_dir / f"{stem}.log"
        child = Child(role, instance, None, log_path, members=members if len(members) > 1 else ())  # type: ignore
        child.proc = self._spawn(child, log_path)
        self.children.append(child)
        return child

    def _spawn(self, child: Child, log_path: Path, extra_env: dict[str, str] | None = None) -> subprocess.Popen:
        env = child_env(child, self.gpu_env, self.role_env, self.instance_env(child.role, child.instance),
                        self.dist_addr, self.train_ranks, self.across_hosts[1] if self.across_hosts else "lo")
        env.update(extra_env or {})
        argv = self.process_argv(child.members) if child.members and self.process_argv else self.argv(
            child.role, child.instance)
        with open(log_path, "ab") as fh:
            return subprocess.Popen(argv, stdout=fh, stderr=subprocess.STDOUT,
                                    stdin=subprocess.DEVNULL, env=env, preexec_fn=_die_with_parent)

    def check(self, restart: bool = True) -> str | None:
        """Notice a child that exited on its own: schedule its restart (when ``restart`` and the policy allows)
        or return the run's failure; start what is due (a scheduled restart, a requota). None: the run goes on."""
        if self.requota_failure is not None:
            return self.requota_failure
        now = time.monotonic()
        for child in self.children:
            if child.given_up:
                continue
            if child.restart_at is not None:
                if now >= child.restart_at:
                    self.restart(child)
                continue
            if child.running():
                continue
            rc = child.proc.returncode
            if child.requota:
                self.restart(child, requota=True)
                continue
            what = f"{child.name} exited with status {rc}"
            if self.across_hosts and child.has("train"):  # the group cannot be started again from here alone
                what += ("; training ranks on several hosts are not restarted (the run stops; ebrl up --resume "
                         "RUN_DIR on the primary goes on from its latest checkpoint)")
            elif restart and self.policy.allows(child.restarts):
                self._schedule_restart(child, what, now)
                continue
            failure = what + (f" (after {child.restarts} restarts)" if child.restarts else "")
            if all(role in self.optional for role, _ in child.services):
                child.given_up = True
                self.event("exited", f"{failure}; the run goes on without it")
                self.say(f"\nebrl: {failure}; the run goes on without it; last lines of {child.log_path}:\n"
                         f"{child.tail(8)}")
                continue
            self.event("exited", failure)
            self.say(f"\nebrl: {failure}; last lines of {child.log_path}:\n{child.tail()}")
            return failure
        return None

    def _schedule_restart(self, child: Child, what: str, now: float) -> None:
        delay = self.policy.delay(child.restarts)
        child.restart_at = now + delay
        if child.role == "train" and self.train_ranks > 1:  # one rank gone breaks the group: restart every rank
            for rank in self.children:
                if rank.role == "train" and rank is not child:
                    if rank.running():
                        _kill_group(rank)
                        rank.proc.wait(5.0)
                    rank.restart_at = now + delay
            self.dist_addr = self.rendezvous()
        limit = self.policy.max_restarts
        self.event("exited", f"{what}; restart {child.restarts + 1}/{limit} in {delay:.0f} s")
        self.say(f"\nebrl: {what}; restarting it in {delay:.0f} s ({child.restarts + 1}/{limit}); "
                 f"last lines of {child.log_path}:\n{child.tail(8)}")

    def restart(self, child: Child, requota: bool = False) -> None:
        """Start ``child`` again: after a failure (counted), or after it stopped for a new GPU share."""
        if requota:
            child.requota = False
            child.requotas += 1
        else:
            child.restarts += 1
        child.restart_at = None
        extra = {}
        # never reuse a version: a new train starts past every one seen; a new gen or eval takes the next
        # versions as plausible from there (ebrl.weights.plausible)
        if any(child.has(role) for role in ("train", "gen", "eval")):
            extra = procenv.service_env(version_floor=self.version_floor())
        why = f"with GPU share {self.gpu_env.get(child.role)}" if requota else f"restart {child.restarts}"
        with open(child.log_path, "ab") as fh:
            fh.write(f"\n--- {why} by the launcher ---\n".encode())
        child.proc = self._spawn(child, child.log_path, extra)
        child.started = time.monotonic()
        if requota:
            self.event("requota", f"{child.name} started again {why}")
        else:
            self.event("restart", f"{child.name} restarted ({child.restarts}/{self.policy.max_restarts})")

    def new_gpu_share(self, role: str, env: dict[str, str], version: int) -> list[Child]:
        """``role``'s processes start with ``env`` from now on; returns those running now, which the caller asks
        to stop at their safe point (each starts again with it once it has exited: :meth:`check`). A share of a
        version ``role`` already had, or the one it has, changes nothing; nor one past :func:`requotas_spent`."""
        if version <= self.share_versions.get(role, 0):
            return []
        self.share_versions[role] = version
        if env == self.gpu_env.get(role) or not any(c.has(role) for c in self.children):
            return []
        if role == "train" and self.train_ranks > 1:
            log.warning("train: a new GPU share is not applied to %d data-parallel ranks (one rank only)",
                        self.train_ranks)
            return []
        if spent := [c for c in self.children if c.has(role) and c.requotas >= self.policy.max_restarts]:
            self.requota_failure = requotas_spent(spent[0], self.policy.max_restarts, version, self.say, self.event)
            return []
        self.gpu_env[role] = env
        asked = [c for c in self.children if c.has(role) and c.running() and not c.requota]
        for child in asked:
            child.requota = True
        return asked

    def kill(self, name: str) -> None:
        """Kill a stuck child's process group (``"gen/0"``: the stall watch, ``ebrl.stall``); :meth:`check` then
        sees it exited and restarts it like any failed child."""
        for child in self.children:
            if name in child.names and child.running():  # a process of several: every service in it
                _kill_group(child)

    def restarts(self) -> dict[str, int]:
        """Restarts after a failure, per child that had any."""
        return {c.name: c.restarts for c in self.children if c.restarts}

    def metrics(self) -> dict[str, float]:
        """``launcher/restarts`` and ``launcher/restarts_<role>`` (summed over the role's instances), for the
        launcher's stats report."""
        out = {"launcher/restarts": float(sum(c.restarts for c in self.children))}
        for c in self.children:
            for role, _ in c.services:
                key = f"launcher/restarts_{role}"
                out[key] = out.get(key, 0.0) + c.restarts
        out["launcher/requotas"] = float(sum(c.requotas for c in self.children))
        return out

    async def shutdown(self, ask_to_stop: Callable[[Child], Awaitable[None]], stop_grace_s: float = STOP_GRACE_S,
                       shutdown_s: float = SHUTDOWN_S) -> None:
        """Stop every child: ``ask_to_stop`` (a ``Stop`` over the bus), SIGTERM after ``stop_grace_s``, SIGKILL to
        its process group at ``shutdown_s``."""
        for child in self.children:
            if child.running():
                await ask_to_stop(child)
        await self._wait_exit(time.monotonic() + stop_grace_s)
        for child in self.children:
            if child.running():
                # a slow teardown (a final checkpoint on a loaded machine): SIGTERM only asks again, the service
                # goes on stopping; said where the launcher logs details, not as a warning on a run that ends well
                log.info("%s still stopping after %.0f s; SIGTERM", child.name, stop_grace_s)
                child.proc.terminate()
        await self._wait_exit(time.monotonic() + shutdown_s - stop_grace_s)
        killed = [c for c in self.children if c.running()]
        for child in killed:
            self.say(f"ebrl: {child.name} ignored SIGTERM; killing it")
            _kill_group(child)
        await self._wait_exit(time.monotonic() + KILL_WAIT_S)  # SIGKILL is not refused, but may take a moment
        for child in killed:
            if child.running():
                self.say(f"ebrl: {child.name} (pid {child.proc.pid}) still there {KILL_WAIT_S:.0f} s after SIGKILL")

    async def _wait_exit(self, deadline: float) -> None:
        while time.monotonic() < deadline and any([c.running() for c in self.children]):  # each one noticed
            await asyncio.sleep(0.05)
