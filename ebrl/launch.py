"""``ebrl up``: validate the config, spawn every service as its own process, supervise, report, shut down.

The launcher is a bus peer like the services: it listens on ``bus.listen``
(services and scripts connect there), watches liveliness tokens to know who is
up, reads ``ebrl/stats/<run>/**`` for the progress line, and stops the run with
``ctl/.../stop`` messages, then SIGTERM, then SIGKILL, so that no process is
left after ``SHUTDOWN_S`` seconds.

In a run over several hosts (``--only``, ``--host``: ``ebrl.hosts``) there is
one launcher per host, started the same way. Each is then a Zenoh *router*: the
services of its host still talk to each other directly, and what crosses hosts
is routed between the launchers. The primary (the host with ``train``) reports
hosts joining and leaving and ends the run for everyone (``ctl/<run>/launcher/
all/stop``); a host whose primary is gone for ``PRIMARY_LOST_S`` stops too.
"""

from __future__ import annotations

import asyncio
import ctypes
import dataclasses
import json
import logging
import os
import signal
import subprocess
import sys
import threading
import time
from pathlib import Path

from ebrl import config as config_mod, procenv
from ebrl.bus import Bus, BusOptions, keys
from ebrl.bus.endpoints import free_port, listen_endpoint
from ebrl.hosts import HostPlan, enabled_roles, plan as plan_host
from ebrl.messages import Event, MessageError, Quota, StatsReport, Stop, decode_message
from ebrl.resources.pool import mps_env
from ebrl.service import STOP_TO_RESTART
from ebrl.viz import record

log = logging.getLogger("ebrl.launch")

STOP_GRACE_S = 5.0  # after the stop message, before SIGTERM
SHUTDOWN_S = 8.0  # after which anything left is SIGKILLed
LOG_TAIL = 20
PRIMARY_LOST_S = 30.0  # a secondary host stops when no train has been live for this long
EVERY_HOST = "all"  # the instance chunk of the run-wide stop: ctl/<run>/launcher/all/stop
PRIMARY_ENDED = "the primary host ended the run"


@dataclasses.dataclass
class Child:
    role: str
    instance: int
    proc: subprocess.Popen
    log_path: Path
    restarts: int = 0
    restart_at: float | None = None  # monotonic time of a scheduled restart
    requota: bool = False  # asked to stop for a new GPU share: started again with it once it has exited

    @property
    def name(self) -> str:
        return f"{self.role}/{self.instance}"

    def tail(self, n: int = LOG_TAIL) -> str:
        try:
            lines = self.log_path.read_text(errors="replace").splitlines()
        except OSError:
            return "(no log)"
        return "\n".join("    " + line for line in lines[-n:])


def make_run_dir(cfg: config_mod.Config) -> Path:
    stamp = time.strftime("%Y%m%d-%H%M%S")
    run_dir = Path(cfg.run.output_dir) / f"{cfg.run.name}-{stamp}"
    suffix = 1
    while run_dir.exists():
        run_dir = Path(cfg.run.output_dir) / f"{cfg.run.name}-{stamp}-{suffix}"
        suffix += 1
    (run_dir / "logs").mkdir(parents=True)
    return run_dir


def _die_with_parent() -> None:  # runs in the child between fork and exec
    os.setpgrp()  # Ctrl-C reaches the launcher only; it stops the children in order
    libc = ctypes.CDLL("libc.so.6", use_errno=True)
    libc.prctl(1, signal.SIGTERM)  # PR_SET_PDEATHSIG: a killed launcher takes its children along


class Launcher:
    def __init__(self, cfg: config_mod.Config, run_dir: Path, out=sys.stdout, plan: HostPlan | None = None,
                 gpu_env: dict[str, dict[str, str]] | None = None):
        self.cfg, self.run_dir, self.out = cfg, run_dir, out
        # stage -> the CUDA variables its processes start with (the allocator's GPU share), and new shares
        # pushed by the allocator (kept by a Zenoh thread, applied by the supervise loop)
        self.gpu_env: dict[str, dict[str, str]] = dict(gpu_env or {})
        self.quota_pending: dict[str, dict[str, str]] = {}
        self.quota_lock = threading.Lock()
        self.plan = plan or HostPlan(enabled_roles(cfg))
        self.run_name = cfg.run.name
        self.dist_addr = ""  # rank 0's rendezvous of the training ranks (train.world_size > 1)
        self.hosts_seen: set[str] = set()  # launcher instances of the other hosts, while up
        self.hosts_joined: set[int] = set()  # ... and every one that joined
        self.ending = False
        self.train_seen_at: float | None = None  # when a train was last live (a secondary waits for it)
        self.children: list[Child] = []
        self.live: set[str] = set()
        self.stats: dict[str, StatsReport] = {}
        self.best_return: float | None = None
        self.failure: str | None = None
        self.reached: tuple[int, float, float] | None = None  # (iteration, seconds, return) at target_return
        self.started = time.monotonic()
        self.tty = hasattr(out, "isatty") and out.isatty()
        self._last_line = 0.0
        self._stats_seq = 0

    async def main(self) -> int:
        self.stopping = asyncio.Event()
        self.stop_reason = ""
        loop = asyncio.get_running_loop()
        for sig in (signal.SIGINT, signal.SIGTERM):
            loop.add_signal_handler(sig, self._on_signal, sig)
        multi = self.plan.multi
        try:
            self.endpoint = listen_endpoint(self.cfg.bus.listen[0], strict=multi) if self.cfg.bus.listen else ""
        except OSError as exc:
            self._say(f"ebrl: {exc}")
            return 2
        listen = [self.endpoint, *self.cfg.bus.listen[1:]] if self.endpoint else []
        self.bus = Bus(BusOptions(mode="router" if multi else "peer", listen=listen,
                                  connect=list(self.cfg.bus.connect), config_file=self.cfg.bus.config_file))
        (self.run_dir / "bus.json").write_text(json.dumps({"listen": listen, "run": self.run_name}) + "\n")
        self.recorder = record.Recorder(self.run_dir / record.FILENAME) if self.cfg.viz.record else None
        if self.recorder is not None:
            self.bus.subscribe_raw(keys.stats_all(self.run_name), self.recorder.write)
        self.bus.watch_liveliness(keys.live_all(self.run_name), self._on_liveliness)
        self.ctl_unknown = 0
        self.bus.subscribe_raw(keys.ctl(self.run_name, "*", "*", "*"), self._on_control)
        me = keys.live(self.run_name, "launcher", self.plan.instance)
        where = f"host {self.plan.name or self.plan.instance}: {', '.join(self.plan.roles)}; " if multi else ""
        bus = self.endpoint or ", ".join(self.cfg.bus.connect)
        self._say(f"run {self.run_name}: {self.run_dir}  ({where}bus {bus})")
        if multi:  # the other hosts' tokens arrive once the routers met: is this host number taken?
            await asyncio.sleep(1.0)
            if me in self.live:
                self._say(f"ebrl: host {self.plan.instance} of run {self.run_name} is already up elsewhere on the "
                          "bus; give each host its own --instance (or --host)")
                await self.bus.close()
                if self.recorder is not None:
                    self.recorder.close()
                return 2
        self.bus.declare_token(me)
        stats_tasks = [asyncio.create_task(self._collect(self.bus.subscribe(
            keys.stats(self.run_name, role, "*"), StatsReport, policy="latest", capacity=64)))
            for role in enabled_roles(self.cfg)]
        code = 1
        try:
            self.spawn_all()
            if await self.wait_live():
                code = await self.supervise()
        finally:
            self.ending = True
            self.event("stopping", self.failure or self.stop_reason or "run finished")
            if multi and self.plan.primary:  # every host ends with the primary
                await self.bus.put(keys.ctl(self.run_name, "launcher", EVERY_HOST, "stop"),
                                   Stop(reason=self.failure or self.stop_reason or "run finished"))
            await self.shutdown()
            for task in stats_tasks:
                task.cancel()
            await self.bus.close()
            if self.recorder is not None:
                self.recorder.close()
        self.write_summary(code)
        self.write_report()
        return code

    def event(self, kind: str, text: str) -> None:
        self.bus.put_nowait(keys.events(self.run_name, "launcher"),
                            Event(time=time.time(), service="launcher", instance=0, kind=kind, text=text))

    # --- processes ----------------------------------------------------------------

    def spawn_all(self) -> None:
        if self.cfg.train.world_size > 1:
            self.dist_addr = f"127.0.0.1:{free_port()}"
        for role in self.plan.roles:
            for instance in self.plan.instances(role, self.cfg):
                log_path = self.run_dir / "logs" / f"{role}-{instance}.log"
                self.children.append(Child(role, instance, self.spawn(role, instance, log_path), log_path))

    def spawn(self, role: str, instance: int, log_path: Path, extra_env: dict[str, str] | None = None
              ) -> subprocess.Popen:
        """Start ``python -m services.<role>``; its output is appended to ``log_path``."""
        env = dict(os.environ, PYTHONUNBUFFERED="1", **self.gpu_env.get(role, {}), **(extra_env or {}))
        if role == "alloc":  # the allocator plans this host's cores: with or without a simulator among them
            env.update(procenv.service_env(local_sim="sim" in self.plan.roles))
        if role == "train":
            env.update(procenv.service_env(dist_addr=self.dist_addr))
        root = str(Path(__file__).resolve().parent.parent)
        env["PYTHONPATH"] = root + os.pathsep + env.get("PYTHONPATH", "")  # `services` beside `ebrl`
        cmd = [sys.executable, "-m", f"services.{role}", "--config", str(self.run_dir / "config.toml"),
               "--instance", str(instance)]
        if self.endpoint:
            cmd += ["--connect", self.endpoint]
        with open(log_path, "ab") as fh:
            return subprocess.Popen(cmd, stdout=fh, stderr=subprocess.STDOUT, stdin=subprocess.DEVNULL,
                                    env=env, preexec_fn=_die_with_parent)

    async def wait_live(self) -> bool:
        wanted = {keys.live(self.run_name, c.role, c.instance) for c in self.children}
        deadline = time.monotonic() + self.cfg.run.startup_timeout
        while not wanted <= self.live:
            if self.stopping.is_set():
                return False
            if self.check_children():
                return False
            if time.monotonic() > deadline:
                missing = sorted(k.split("/", 3)[3] for k in wanted - self.live)
                self.failure = f"not up after {self.cfg.run.startup_timeout:.0f} s: {', '.join(missing)}"
                self._say("ebrl: " + self.failure)
                for child in self.children:
                    if keys.live(self.run_name, child.role, child.instance) not in self.live:
                        self._say(f"--- last lines of {child.log_path}:\n{child.tail()}")
                return False
            await asyncio.sleep(0.05)
        self._say(f"all services live after {time.monotonic() - self.started:.1f} s: "
                  + ", ".join(c.name for c in self.children))
        self.event("live", f"{', '.join(c.name for c in self.children)} live after "
                           f"{time.monotonic() - self.started:.1f} s")
        if self.cfg.viz.rerun != "off":
            self._say(f"viz: rerun {self.cfg.viz.rerun} -> {self.run_dir / 'timeline.rrd'}"
                      + (f" (viewer: rerun --connect rerun+http://127.0.0.1:{self.cfg.viz.port}/proxy)"
                         if self.cfg.viz.rerun == "serve" else ""))
        return True

    def check_children(self, restart: bool = False) -> bool:
        """Notice a child that exited on its own: restart it (``run.restart``, with backoff, at most
        ``run.max_restarts`` times) when ``restart``, else report it; True when the run must stop. A child
        that stopped for a new GPU share starts again with it at once (no restart counted)."""
        self.apply_gpu_quotas()
        now = time.monotonic()
        for child in self.children:
            if child.restart_at is not None:
                if now >= child.restart_at:
                    self.restart(child)
                continue
            rc = child.proc.poll()
            if rc is None:
                continue
            if child.requota:
                self.restart(child, requota=True)
                continue
            what = f"{child.name} exited with status {rc}"
            if restart and self.cfg.run.restart == "on-failure" and child.restarts < self.cfg.run.max_restarts:
                delay = min(2.0 ** child.restarts, 30.0)
                child.restart_at = now + delay
                if child.role == "train" and self.dist_addr:  # one rank gone breaks the group: restart every rank
                    for rank in self.children:
                        if rank.role == "train" and rank is not child:
                            if rank.proc.poll() is None:
                                os.killpg(rank.proc.pid, signal.SIGKILL)
                                rank.proc.wait(5.0)
                            rank.restart_at = now + delay
                    self.dist_addr = f"127.0.0.1:{free_port()}"
                self.event("exited", f"{what}; restart {child.restarts + 1}/{self.cfg.run.max_restarts} in "
                                     f"{delay:.0f} s")
                self._say(f"\nebrl: {what}; restarting it in {delay:.0f} s "
                          f"({child.restarts + 1}/{self.cfg.run.max_restarts}); last lines of {child.log_path}:"
                          f"\n{child.tail(8)}")
                continue
            self.failure = what + (f" (after {child.restarts} restarts)" if child.restarts else "")
            self.event("exited", self.failure)
            self._say(f"\nebrl: {self.failure}; last lines of {child.log_path}:\n{child.tail()}")
            return True
        return False

    def restart(self, child: Child, requota: bool = False) -> None:
        """Start ``child`` again: after a failure (counted), or after it stopped for a new GPU share."""
        if requota:
            child.requota = False
        else:
            child.restarts += 1
        child.restart_at = None
        extra = {}
        if child.role == "train":  # never reuse a version: the new train starts past every one seen
            extra = procenv.service_env(
                version_floor=max(self.version(), int(self.metric("gen/policy_version", "max") or 0)))
        why = f"with GPU share {self.gpu_env.get(child.role)}" if requota else f"restart {child.restarts}"
        with open(child.log_path, "ab") as fh:
            fh.write(f"\n--- {why} by the launcher ---\n".encode())
        child.proc = self.spawn(child.role, child.instance, child.log_path, extra)
        if requota:
            self.event("requota", f"{child.name} started again {why}")
        else:
            self.event("restart", f"{child.name} restarted ({child.restarts}/{self.cfg.run.max_restarts})")

    def on_gpu_quota(self, role: str, quota: Quota) -> None:
        """(Zenoh thread) The allocator gave ``role`` a new GPU share: remembered for the supervise loop."""
        if quota.sm_percent is None or role not in ("gen", "train") or role not in self.gpu_env:
            return
        current = self.gpu_env[role]
        env = {**current, **mps_env(int(current.get("CUDA_VISIBLE_DEVICES", "0")), quota.sm_percent,
                                    quota.mem_bytes or 0)}
        if not quota.mem_bytes:  # no new memory budget: the one it has
            env["CUDA_MPS_PINNED_DEVICE_MEM_LIMIT"] = current.get("CUDA_MPS_PINNED_DEVICE_MEM_LIMIT", "")
            env = {k: v for k, v in env.items() if v}
        with self.quota_lock:
            self.quota_pending[role] = env

    def apply_gpu_quotas(self) -> None:
        """A GPU share takes a new process (MPS reads it when the CUDA context is made): ask the stage's
        processes to stop at their safe boundary -- generation between batches, training after its update,
        with its state in a checkpoint that the new process resumes from -- and start them again with it."""
        with self.quota_lock:
            pending, self.quota_pending = self.quota_pending, {}
        for role, env in pending.items():
            if env == self.gpu_env.get(role):
                continue
            if role == "train" and self.cfg.train.world_size > 1:
                log.warning("train: a new GPU share is not applied to %d data-parallel ranks (one rank only)",
                            self.cfg.train.world_size)
                continue
            self.gpu_env[role] = env
            for child in self.children:
                if child.role == role and child.proc.poll() is None and not child.requota:
                    child.requota = True
                    self.bus.put_nowait(keys.ctl(self.run_name, role, child.instance, "stop"),
                                        Stop(reason=STOP_TO_RESTART))

    def restarts(self) -> int:
        return sum(c.restarts for c in self.children)

    def publish_stats(self) -> None:
        """The launcher's own stats report: restarts per service, services up."""
        metrics = {"launcher/restarts": float(self.restarts()), "launcher/ctl_unknown_service": float(self.ctl_unknown),
                   "launcher/services_live": float(sum(1 for k in self.live if "/launcher/" not in k))}
        metrics.update({f"launcher/restarts_{c.role}": float(c.restarts) for c in self.children})
        self.bus.put_nowait(keys.stats(self.run_name, "launcher", 0), StatsReport(
            run=self.run_name, service="launcher", instance=0, time=time.time(), seq=self._stats_seq,
            metrics=metrics))
        self._stats_seq += 1

    async def supervise(self) -> int:
        target = self.cfg.run.iterations
        last_stats = 0.0
        while not self.stopping.is_set():
            if self.check_children(restart=True):
                return 1
            if time.monotonic() - last_stats >= self.cfg.run.stats_interval:
                self.publish_stats()
                last_stats = time.monotonic()
            self.progress()
            if not self.plan.primary:
                if self.primary_lost():
                    return 1
            elif target and self.version() >= target:
                self.progress(force=True)
                return 0
            goal, ret = self.cfg.run.target_return, self.metric("sim/episode_return_mean", "mean")
            if self.plan.primary and goal is not None and ret is not None and ret >= goal:
                self.progress(force=True)
                self.reached = (self.version(), time.monotonic() - self.started, ret)
                self._say(f"reached run.target_return = {goal:g}: mean return {ret:.1f} at iteration "
                          f"{self.version()} after {self.reached[1]:.0f} s")
                return 0
            try:
                await asyncio.wait_for(self.stopping.wait(), 0.5)
            except asyncio.TimeoutError:
                pass
        if self.stop_reason == PRIMARY_ENDED:
            return 0
        return 130 if self.stop_reason.startswith("signal SIGINT") else 143

    def primary_lost(self) -> bool:
        """A secondary host: True (and the failure said) once the run's train has been gone too long."""
        if any(keys.role_of(k) == "train" for k in self.live):
            self.train_seen_at = time.monotonic()
            return False
        if self.train_seen_at is None or time.monotonic() - self.train_seen_at < PRIMARY_LOST_S:
            return False
        self.failure = f"no train on the bus for {PRIMARY_LOST_S:.0f} s: the primary host is gone"
        self._say(f"\nebrl: {self.failure}")
        return True

    async def shutdown(self) -> None:
        if self.tty:
            self.out.write("\n")
        running = [c for c in self.children if c.proc.poll() is None]
        for child in running:
            await self.bus.put(keys.ctl(self.run_name, child.role, child.instance, "stop"),
                               Stop(reason=self.stop_reason or "run finished"))
        deadline = time.monotonic() + STOP_GRACE_S
        await self._wait_exit(deadline)
        for child in self.children:
            if child.proc.poll() is None:
                log.warning("%s did not stop in %.0f s; SIGTERM", child.name, STOP_GRACE_S)
                child.proc.terminate()
        await self._wait_exit(time.monotonic() + SHUTDOWN_S - STOP_GRACE_S)
        for child in self.children:
            if child.proc.poll() is None:
                self._say(f"ebrl: {child.name} ignored SIGTERM; killing it")
                os.killpg(child.proc.pid, signal.SIGKILL)
                child.proc.wait(1.0)

    async def _wait_exit(self, deadline: float) -> None:
        while time.monotonic() < deadline and any(c.proc.poll() is None for c in self.children):
            await asyncio.sleep(0.05)

    # --- bus events ---------------------------------------------------------------

    def _on_signal(self, sig: signal.Signals) -> None:
        if not self.stopping.is_set():
            self.stop_reason = f"signal {sig.name}"
            self._say(f"\nebrl: {sig.name} received, stopping every service")
            self.stopping.set()

    def _on_control(self, key: str, payload: bytes) -> None:
        """Control messages for a service this run does not have are ignored by everyone; counted here.
        A secondary host's launcher stops when the primary ends the run."""
        role = keys.role_of(key)
        if role == "launcher":
            if self.plan.multi and not self.plan.primary and key.endswith("/stop") and not self.stopping.is_set():
                self.stop_reason = PRIMARY_ENDED
                self._say(f"\nebrl: {self.stop_reason}; stopping this host's services")
                self.stopping.set()
            return
        if key.endswith("/quota") and self.gpu_env:
            try:
                self.on_gpu_quota(role, decode_message(Quota, payload))
            except MessageError:
                pass  # counted by the service it was meant for
        if role not in enabled_roles(self.cfg):
            if not self.ctl_unknown:
                log.warning("control message for an unknown service ignored: %s (further ones only counted)", key)
            self.ctl_unknown += 1

    def _on_liveliness(self, key: str, alive: bool) -> None:
        if alive:
            self.live.add(key)
        else:
            self.live.discard(key)
        parsed = keys.parse(key)
        role, instance = parsed.service, parsed.instance
        other_host = role == "launcher" and instance.isdigit() and instance != str(self.plan.instance)
        if not (self.plan.multi and other_host):
            return
        if alive and instance not in self.hosts_seen:
            self.hosts_seen.add(instance)
            self.hosts_joined.add(int(instance))
            self._say(f"\nebrl: host {instance} joined the run")
            self.event("host", f"host {instance} joined the run")
        elif not alive and instance in self.hosts_seen and not self.ending:
            self.hosts_seen.discard(instance)
            self._say(f"\nebrl: host {instance} left the run; nothing waits for its groups")
            self.event("host", f"host {instance} left the run")

    async def _collect(self, sub) -> None:
        async for key, report in sub:
            self.stats[key] = report

    # --- progress -----------------------------------------------------------------

    def metric(self, name: str, how: str = "sum") -> float | None:
        values = [r.metrics[name] for r in self.stats.values() if name in r.metrics]
        if not values:
            return None
        return sum(values) if how == "sum" else (max(values) if how == "max" else sum(values) / len(values))

    def version(self) -> int:
        return int(self.metric("train/policy_version", "max") or 0)

    def progress(self, force: bool = False) -> None:
        ret = self.metric("sim/episode_return_mean", "mean")
        if ret is not None:
            self.best_return = ret if self.best_return is None else max(self.best_return, ret)
        target = self.cfg.run.iterations
        fields = [
            f"iter {self.version()}" + (f"/{target}" if target else ""),
            f"{self.metric('sim/env_steps_per_s') or 0:,.0f} env steps/s",
            f"{self.metric('sim/segments_per_s') or 0:,.1f} traj/s",
            f"policy v{max(int(self.metric('gen/policy_version', 'max') or 0), 0)}",
            f"staleness {self.metric('train/staleness_mean', 'mean') or 0:.2f}",
            f"return {ret:.1f}" if ret is not None else "return -",
            *([f"restarts {self.restarts()}"] if self.restarts() else []),
            *([f"hosts {len(self.hosts_seen) + 1}"] if self.plan.multi else []),
            _clock(time.monotonic() - self.started),
        ]
        line = " | ".join(fields)
        if self.tty:
            self.out.write("\r\033[K" + line)
            self.out.flush()
        elif force or time.monotonic() - self._last_line >= 5.0:
            self._say(line)
            self._last_line = time.monotonic()

    def _say(self, text: str) -> None:
        if self.tty:
            text = "\r\033[K" + text.lstrip("\n")
        print(text, file=self.out, flush=True)

    def write_summary(self, code: int) -> None:
        elapsed = time.monotonic() - self.started
        steps = self.metric("sim/env_steps") or 0
        summary = {
            "run": self.run_name,
            "run_dir": str(self.run_dir),
            "exit_code": code,
            "failure": self.failure,
            "iterations": self.version(),
            "wall_s": round(elapsed, 2),
            "env_steps": int(steps),
            "env_steps_per_s": round(steps / elapsed, 1) if elapsed > 0 else 0.0,
            "segments": int(self.metric("sim/segments") or 0),
            "episodes": int(self.metric("sim/episodes") or 0),
            "final_return": self.metric("sim/episode_return_mean", "mean"),
            "best_return": self.best_return,
            "target_return": self.cfg.run.target_return,
            "restarts": {c.name: c.restarts for c in self.children if c.restarts},
            "host": self.plan.instance,
            "hosts": sorted(self.hosts_joined | {self.plan.instance}),  # every host that took part
            "target_reached": None if self.reached is None else
            {"iteration": self.reached[0], "wall_s": round(self.reached[1], 2), "return": self.reached[2]},
        }
        (self.run_dir / "summary.json").write_text(json.dumps(summary, indent=2) + "\n")
        final = f"{summary['final_return']:.1f}" if summary["final_return"] is not None else "-"
        best = f"{summary['best_return']:.1f}" if summary["best_return"] is not None else "-"
        self._say(f"run {self.run_name} {'finished' if code == 0 else 'stopped'}: {summary['iterations']} iterations "
                  f"in {elapsed:.0f} s, {summary['env_steps']:,} env steps ({summary['env_steps_per_s']:,.0f}/s), "
                  f"mean return {final} (best {best}); summary in {self.run_dir / 'summary.json'}")

    def write_report(self) -> None:
        """The headless report of the run (``ebrl report``), from the recording; never fails the run."""
        if not (self.cfg.viz.report and self.recorder is not None and self.recorder.samples):
            return
        from ebrl.viz import report

        try:
            paths = report.write(self.run_dir)
        except Exception as exc:  # a report is a convenience: say why, keep the exit code
            self._say(f"ebrl: no report: {exc}")
            return
        self._say(f"report: {paths['markdown']} (Gantt: {paths['gantt']})")


def _clock(seconds: float) -> str:
    s = int(seconds)
    return f"{s // 3600}:{s // 60 % 60:02d}:{s % 60:02d}"


def preflight(cfg: config_mod.Config) -> str | None:
    """What would make the run fail at start, found before any process starts (None: nothing)."""
    from ebrl.envs import EnvError, EnvSpec, preflight as env_preflight

    if cfg.policy.checkpoint and not os.path.isfile(cfg.policy.checkpoint):
        return f"policy.checkpoint = {cfg.policy.checkpoint!r}: no such file"
    try:
        env_preflight(EnvSpec.from_config(cfg.env))  # e.g. ManiSkill without a GPU; picks the GL backend for cameras
    except EnvError as exc:
        return str(exc)
    return None


def up(config_path: str, overrides: list[str], viz: str | None = None, resume: str | None = None,
       only: str | None = None, host: str | None = None, instance: int | None = None) -> int:
    """``ebrl up``: exit 2 on a config error (nothing started), else the run's exit code.
    ``viz`` (``--viz``) sets ``viz.rerun``; ``resume`` (``--resume RUN_DIR``) continues that run;
    ``only``/``instance`` or ``host`` start this host's part of a run over several hosts."""
    if viz is not None:
        overrides = [*overrides, f'viz.rerun="{viz}"']
    try:
        cfg = config_mod.load(config_path, overrides)
        cfg, plan = plan_host(cfg, only=only, host=host, instance=instance)
    except config_mod.ConfigError as exc:
        print(f"ebrl: config error: {exc}", file=sys.stderr)
        return 2
    problem = preflight(cfg)
    if problem:
        print(f"ebrl: {problem}", file=sys.stderr)
        return 2
    gpu_env: dict[str, dict[str, str]] = {}
    if "alloc" in plan.roles:  # profile (or reuse a profile) and start every service inside Algorithm 1's plan
        from ebrl.alloc.algorithm import InfeasibleError
        from ebrl.alloc.runtime import initial_config
        from ebrl.resources.pool import ResourceError

        try:
            cfg, gpu_env, line = initial_config(cfg, local_sim="sim" in plan.roles)
        except (InfeasibleError, ResourceError) as exc:
            print(f"ebrl: allocator: {exc}", file=sys.stderr)
            return 2
        print(line, flush=True)
    if resume is not None:
        from ebrl.algos import checkpoint

        run_dir = Path(resume)
        found = checkpoint.latest(run_dir)
        if found is None:
            print(f"ebrl: --resume {resume}: no checkpoint there ({run_dir / checkpoint.DIRNAME}/latest)",
                  file=sys.stderr)
            return 2
        print(f"resuming {run_dir} from {found.name}", flush=True)
    else:
        run_dir = make_run_dir(cfg)
    (run_dir / "config.toml").write_text(config_mod.dump_toml(cfg))
    logging.basicConfig(level=logging.WARNING, format="%(levelname)s %(name)s: %(message)s")
    return asyncio.run(Launcher(cfg, run_dir, plan=plan, gpu_env=gpu_env).main())
