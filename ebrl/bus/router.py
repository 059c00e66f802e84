"""``ebrl router``: a Zenoh router that hosts meet at.

The launchers of a run over several hosts route between each other, so a
router is optional: point every host's ``bus.connect`` at one host's ``listen``
endpoint, or at an ``ebrl router`` that all of them can reach (a fixed address
to configure once, a host that stays up between runs, a place to put TLS and
access control through ``--config``). Same engine as ``zenohd``, without
installing it. It prints the EBRL services that join and leave.
"""

from __future__ import annotations

import signal
import sys
import threading
import time

import zenoh

from ebrl import graph, keys
from ebrl.bus import auth
from ebrl.bus.session import BusOptions
from ebrl.bus.endpoints import config_file_acl, config_file_endpoints, config_file_listen
from ebrl.bus.session import zenoh_config
from ebrl.bus.zlog import ZenohLog


def serve(listen: list[str], connect: list[str], config_file: str = "", quiet: bool = False, out=None,
          secret: str = "", insecure: bool = False) -> int:
    """Run until SIGINT/SIGTERM; exit status 2 when an endpoint cannot be opened or would be plain beyond this
    host (``insecure`` allows it, with a warning). ``secret``: the run's secret file; only its holders join. A
    host it refuses (TLS, sign-in) is said with the time (``ebrl.bus.zlog``)."""
    try:
        listen = config_file_listen(config_file) or listen  # the file's endpoints are never replaced
        every = config_file_endpoints(config_file) + listen + connect  # each endpoint zenoh will use, checked
        if secret and config_file_acl(config_file):
            raise auth.AuthError(f"{config_file} turns on access_control, and with --secret the router sets its "
                                 "own (each role's rights, ebrl.graph); it cannot merge the two: remove the block, "
                                 "or leave out --secret to run with yours alone")
        conf = zenoh_config(BusOptions(mode="router", listen=listen, connect=connect, config_file=config_file,
                                       secret_file=secret, file_listen_wins=True, role="launcher", host="router"))
    except (auth.AuthError, zenoh.ZError) as exc:
        print(f"ebrl router: {exc}", file=sys.stderr)
        return 2
    refused = auth.check_endpoints(every, insecure, "ebrl router")
    if refused:
        print(refused, file=sys.stderr)
        return 2
    if auth.insecure_endpoints(every):
        print(f"ebrl router: warning: --insecure: {', '.join(auth.insecure_endpoints(every))} carry "
              "the run's data unencrypted", file=sys.stderr)
    if not secret:
        print("ebrl router: no --secret: any process that reaches these endpoints can join", file=sys.stderr)
    zlog = ZenohLog()
    zlog.start()
    out = out or sys.stdout  # after the log's start: sys.stdout is then a new object
    zlog.on_refusal = lambda line: print(f"{time.strftime('%H:%M:%S')} {line}", file=out, flush=True)
    try:
        session = zenoh.open(conf)
    except zenoh.ZError as exc:
        print(f"ebrl router: cannot open {', '.join(listen)}: {exc}", file=sys.stderr)
        zlog.stop()
        return 2
    done = threading.Event()
    for sig in (signal.SIGINT, signal.SIGTERM):
        signal.signal(sig, lambda *_: done.set())

    def on_token(sample: zenoh.Sample) -> None:  # ebrl/live/<run>/<service>/<instance>
        key = keys.parse(sample.key_expr)
        run, service, instance = key.run, key.service, key.instance
        verb = "joined" if sample.kind == zenoh.SampleKind.PUT else "left"
        print(f"{time.strftime('%H:%M:%S')} run {run}: {service}/{instance} {verb}", file=out, flush=True)

    watcher = None if quiet else session.liveliness().declare_subscriber(
        graph.every_token(), on_token, history=True)
    print(f"ebrl router {session.info.zid()} listening on {', '.join(listen)}"
          + (f", connected to {', '.join(connect)}" if connect else ""), file=out, flush=True)
    done.wait()
    if watcher is not None:
        watcher.undeclare()
    session.close()
    zlog.stop()
    return 0
