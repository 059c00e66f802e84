"""How a process joins the bus: :class:`BusOptions` (built from the ``[bus]`` config section) and the Zenoh config
made of them (:func:`zenoh_config`): mode, endpoints, sign-in and access control (:mod:`ebrl.bus.auth`)."""

from __future__ import annotations

import json
from dataclasses import dataclass, field
from typing import Literal

import zenoh

from ebrl.bus import auth
from ebrl.bus.endpoints import config_file_connect, config_file_listen


@dataclass
class BusOptions:
    """How to join the bus. Built from the ``[bus]`` config section."""

    mode: Literal["peer", "client", "router"] = "peer"  # router: a launcher joining hosts
    connect: list[str] = field(default_factory=list)
    listen: list[str] = field(default_factory=lambda: ["tcp/127.0.0.1:0"])
    config_file: str = ""
    max_message_bytes: int = 256 << 20  # larger payloads are dropped before decoding (Zenoh's own rx limit too)
    secret_file: str = ""  # the run's secret (ebrl.bus.auth); empty: an open bus that anyone on the host can join
    role: str = ""  # who signs in (with a secret_file): a role of the service graph, or observer (a script watching)
    run: str = "*"  # the run whose keys a router's access rules name (ebrl.graph.access_control)
    # a launcher's host number, or "router" for ebrl router: a router signed in that opens no link of its own
    # takes that host's Zenoh id (ebrl.bus.auth.host_zid), which the hosts that connect to it trust
    host: int | str | None = None
    file_listen_wins: bool = False  # the listen endpoints of config_file, when it has some, replace ``listen``
    local: str = ""  # a loopback endpoint listened on in any case (a launcher's, for its own services)
    # ``user:password`` of this process's own instance identity, handed over by its launcher (ebrl.procenv): a
    # client signs in with it rather than with its role's line of secret_file (ebrl.bus.auth)
    identity: str = ""
    # a client-mode launcher's router: the service instances it starts ((role, n) pairs), each admitted with its
    # own identity and rights, checked against dictionary_file (ebrl.bus.auth.write_router_dictionary); and the
    # groups each simulator has (its data keys are its own groups'); empty: every role's line, any instance
    instances: tuple[tuple[str, int], ...] = ()
    dictionary_file: str = ""
    groups: int = 0
    # ... and every instance of the run on every host (launchers included), where its plan names them: tokens of
    # any other instance then reach this router's own session alone, where the launcher counts them
    planned: tuple[tuple[str, int], ...] | None = None
    # ... and the processes of several services it starts (run.processes): the first service of each, one of
    # ``instances``, signs in for all of them and may send what each may
    shares: tuple[tuple[tuple[str, int], ...], ...] = ()


# Zenoh's default has both peers of a pair connect to each other as soon as gossip tells them of the other.
# The two sessions race; with usrpwd (bus.auth) zenoh 1.10 rejects the second one as a duplicate of a
# different configuration (eclipse-zenoh/zenoh#2577), and a pair of peers could end with no session at all,
# never hearing each other (a run stalled at start). One side connecting ends the race (tests/test_bus.py
# holds the check; the counts are in the commit that made it so).
AUTOCONNECT_STRATEGY = {"peer": {"to_router": "always", "to_peer": "greater-zid"}}


def zenoh_config(options: BusOptions) -> zenoh.Config:
    """A Zenoh config: loopback-only peer unless told otherwise, multicast scouting off; with a
    ``secret_file``, signed in as ``role`` and, as a router or peer, access-controlled (:mod:`ebrl.bus.auth`);
    with an ``identity`` (a service its launcher started), signed in as its own instance.

    Peers learn each other's loopback locators by gossip through the endpoint they
    connect to (the launcher's), so services talk directly, without a relay. Of two peers that learn of each
    other, only the one with the greater Zenoh id connects (:data:`AUTOCONNECT_STRATEGY`).
    """
    conf = zenoh.Config.from_file(options.config_file) if options.config_file else zenoh.Config()
    conf.insert_json5("mode", json.dumps(options.mode))
    conf.insert_json5("scouting/multicast/enabled", "false")
    if json.loads(conf.get_json("scouting/gossip/autoconnect_strategy")) is None:  # unless config_file says
        conf.insert_json5("scouting/gossip/autoconnect_strategy", json.dumps(AUTOCONNECT_STRATEGY))
    file_listen = config_file_listen(options.config_file)  # none where the file leaves the default (every address)
    listen = file_listen if options.file_listen_wins and file_listen else options.listen
    listen = [*listen, options.local] if options.local and options.local not in listen else listen
    if listen and options.mode != "client" and listen is not file_listen:
        conf.insert_json5("listen/endpoints", json.dumps(listen))
    if options.connect:
        conf.insert_json5("connect/endpoints", json.dumps(options.connect))
    # Zenoh reassembles no message larger than this (it drops it, the link stays): the same bound as ours
    conf.insert_json5("transport/link/rx/max_message_size", json.dumps(options.max_message_bytes))
    if options.identity:
        credentials = auth.parse_line(options.identity)
        own = auth.instance_of(credentials.user)
        if options.mode != "client" or own is None or (options.role and own[0] != options.role):
            raise auth.AuthError(f"{credentials.user!r} is no identity of a {options.role or 'service'} instance "
                                 f"(it signs in as a client of its launcher, not as a {options.mode})")
        conf.insert_json5("transport/auth/usrpwd", json.dumps(auth.zenoh_settings(credentials, "client")
                                                               ["transport/auth/usrpwd"]))
    elif options.secret_file:
        if not options.role:
            raise auth.AuthError("signing in needs a role (BusOptions.role): a role of the service graph or "
                                 "observer")
        credentials = auth.load(options.secret_file, options.role)
        connects = options.mode == "router" and bool(options.connect or config_file_connect(options.config_file))
        for path, value in auth.zenoh_settings(credentials, options.mode, options.run, connects, options.instances,
                                               options.dictionary_file or None, options.groups,
                                               options.planned, options.shares).items():
            conf.insert_json5(path, json.dumps(value))
        if options.mode == "router" and not connects and options.host is not None:
            conf.insert_json5("id", json.dumps(auth.host_zid(options.secret_file, options.host)))
    return conf
