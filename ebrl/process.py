"""Several services in one process (``run.processes``): ``python -m ebrl.process --service sim/0 --service gen/0 ...``.

The launcher starts one of these for each group of services that ``run.processes`` places together on its host
(``ebrl.hosts.HostPlan.processes``). Each service keeps everything it has in a process of its own: its event loop
(on a thread of its own, so that one service's work never holds another's loop), its liveliness token, stats
reports, Gantt lanes, control keys and version numbers. What they share is the process and one Zenoh session,
signed in with the first service's identity, to which the launcher's router grants what each service of the
process may send (``ebrl.graph.access_control``). Between the services of the process, messages go by reference
(:mod:`ebrl.bus.local`): no encoding, no copy, no socket; Zenoh carries only what other processes subscribe to.

The process ends when its services have: once one stops (a ``Stop``, a failure), the others are asked to stop
too, so that the launcher sees one process exit and starts it again with every service in it, as it does one
service. SIGINT/SIGTERM stop them all.
"""

from __future__ import annotations

import argparse
import asyncio
import dataclasses
import importlib
import logging
import os
import signal
import sys
import threading

import zenoh

from ebrl import config as config_mod, graph, procenv, sizes
from ebrl.bus import auth
from ebrl.bus.local import LocalBus, LocalHub
from ebrl.bus.session import BusOptions, zenoh_config
from ebrl.service import EXIT_GRACE_S, Service, exit_within, bounded

log = logging.getLogger("ebrl.process")


def service_class(role: str) -> type[Service]:
    """The :class:`Service` of ``role`` (its module, ``ebrl.graph.Role.module``: ``ebrl.services.<role>``)."""
    module = importlib.import_module(graph.ROLES[role].module)
    for value in vars(module).values():
        if isinstance(value, type) and issubclass(value, Service) and value is not Service and value.role == role:
            return value
    raise ValueError(f"ebrl.services.{role} has no Service of role {role!r}")


def parse_service(text: str) -> tuple[str, int]:
    """``"sim/0"`` -> ``("sim", 0)``."""
    role, _, instance = text.partition("/")
    if not instance.isdigit():
        raise argparse.ArgumentTypeError(f"{text!r}: a service is ROLE/INSTANCE, e.g. sim/0")
    return role, int(instance)


class SharedProcess:
    """The services of one process, each on its own thread and event loop, over one shared Zenoh session."""

    def __init__(self, services: list[Service], options: BusOptions):
        self.services, self.options = services, options
        for service in services:
            service.shares_process = len(services) > 1  # the simulator's vectorized groups then step in it too
        if len(services) > 1 and any(s.role == "gen" for s in services):  # its chunk forward may be captured
            from ebrl.policies import graphs

            graphs.CAPTURE_ERROR_MODE = "thread_local"
        self.hub = LocalHub(services[0].run_name)  # who in the process subscribes to what
        self.loops: dict[int, asyncio.AbstractEventLoop] = {}
        self.codes: dict[int, int] = {}
        self.stop_reason: str | None = None  # once set, every service stops (or stops as soon as it starts)
        self._lock = threading.RLock()  # stop_all runs in signal handlers too, which may interrupt it

    def open_session(self) -> zenoh.Session:
        """The process's session: Zenoh's receive limit the largest of its services' bounds (each service's bus
        still refuses what is over its own keys' bounds)."""
        async def read() -> list[sizes.Bounds | None]:
            return list(await asyncio.gather(*(s.message_bounds() for s in self.services)))

        for service, bounds in zip(self.services, asyncio.run(read())):
            service.bounds = bounds
        known = [s.bounds for s in self.services if s.bounds is not None]
        options = self.options
        if known and len(known) == len(self.services):
            options = dataclasses.replace(options, max_message_bytes=min(options.max_message_bytes,
                                                                         max(b.link for b in known)))
        return zenoh.open(zenoh_config(options))

    def run(self) -> int:
        """Run every service to its end; the process's exit status (the worst of theirs)."""
        session = self.open_session()
        threads = [threading.Thread(target=self._serve, args=(i, session), name=f"{s.role}/{s.instance}")
                   for i, s in enumerate(self.services)]
        for sig in (signal.SIGINT, signal.SIGTERM):
            signal.signal(sig, lambda signum, _: self.stop_all(f"signal {signal.Signals(signum).name}"))
        for index in self.start_order():  # one at a time: no CUDA capture of one meets another's set-up
            threads[index].start()
            while threads[index].is_alive() and not self.services[index].ready.wait(0.2):
                pass
        for thread in threads:
            while thread.is_alive():
                thread.join(0.2)  # the main thread stays free for the signal handlers
        try:
            session.close()
        except Exception as exc:
            log.debug("session close: %s", exc)
        return max(self.codes.values(), default=1)

    def start_order(self) -> list[int]:
        """The simulator first (its vectorized groups build their batches, and capture their CUDA graphs, while
        nothing else of the process uses the GPU), then the others in their order."""
        return sorted(range(len(self.services)), key=lambda i: self.services[i].role != "sim")

    def _serve(self, index: int, session: zenoh.Session) -> None:
        service = self.services[index]

        async def serve() -> int:
            with self._lock:
                self.loops[index] = asyncio.get_running_loop()
                if self.stop_reason is not None:  # asked before this loop was there: stop once started
                    self.loops[index].call_soon(service.request_stop, self.stop_reason)
            options = bounded(dataclasses.replace(service.bus_options, role=service.role), service.bounds)
            bus = LocalBus(options, session=session, hub=self.hub, instance=service.instance)
            return await service.main(bus=bus, signals=False)

        try:
            code = asyncio.run(serve())
        except BaseException:
            log.exception("%s/%d failed", service.role, service.instance)
            code = 1
        self.codes[index] = code
        self.stop_all(f"{service.role}/{service.instance} in this process stopped")

    def stop_all(self, reason: str) -> None:
        """Ask every service of the process to stop (from any thread)."""
        with self._lock:
            self.stop_reason = self.stop_reason or reason
            loops = dict(self.loops)
        for index, loop in loops.items():
            if index not in self.codes:  # request_stop runs once main() has made its event: main's first step
                try:
                    loop.call_soon_threadsafe(self.services[index].request_stop, reason)
                except RuntimeError:  # its loop has closed: it has stopped
                    pass


def main(argv: list[str] | None = None) -> None:
    """Entry point of ``python -m ebrl.process``."""
    parser = argparse.ArgumentParser(prog="ebrl.process", description=__doc__.splitlines()[0])
    parser.add_argument("--config", required=True, help="resolved TOML config")
    parser.add_argument("--service", action="append", type=parse_service, required=True, dest="services",
                        metavar="ROLE/N", help="a service of this process (the first signs in for it)")
    parser.add_argument("--connect", action="append", default=[], help="bus endpoint to connect to")
    args = parser.parse_args(argv)
    try:
        cfg = config_mod.load(args.config, [])
    except config_mod.ConfigError as exc:
        print(f"config error: {exc}", file=sys.stderr)
        sys.exit(2)
    logging.basicConfig(level=cfg.run.log_level.upper(),
                        format="%(asctime)s %(threadName)s %(levelname)s %(name)s: %(message)s")
    run_dir = os.path.dirname(os.path.abspath(args.config))
    lead = args.services[0][0]
    options = BusOptions(mode=cfg.bus.mode, connect=args.connect or list(cfg.bus.connect), listen=["tcp/127.0.0.1:0"],
                         config_file=cfg.bus.config_file, max_message_bytes=cfg.bus.max_message_bytes,
                         secret_file=auth.secret_path(cfg.bus, run_dir), role=lead,
                         identity=procenv.take_identity())  # the first service's, from its launcher
    services = [service_class(role)(cfg, instance, dataclasses.replace(options, role=role), run_dir=run_dir)
                for role, instance in args.services]
    code = SharedProcess(services, options).run()
    exit_within(EXIT_GRACE_S, code, "+".join(f"{s.role}/{s.instance}" for s in services))
    sys.exit(code)


if __name__ == "__main__":
    main()
