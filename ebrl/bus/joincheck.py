"""Why a host cannot join a run, found by the host itself.

A launcher that connects to another host (its learner's ``listen`` endpoint, or an ``ebrl router``) and has no
link to it a few seconds after its bus opened (:data:`JOIN_CHECK_S`) looks for the cause on each endpoint it
connects to (:func:`diagnose`), the way Zenoh would meet it: the address (resolved, routed, listened on), the TLS
handshake against the CA of ``bus.config_file`` (its ``root_ca_certificate``; the system's CAs where it names
none), then the sign-in, which is all that is left when the handshake goes through. ``ebrl up`` says the cause
and exits 2 (:class:`Cause` ``final``), or, where nothing listens there yet (the learner may still be starting),
says so and keeps trying until ``run.startup_timeout``.

Certificates the config file names are checked before anything starts (:func:`certificate_problem`): a missing
or unreadable file is a config error naming it.
"""

from __future__ import annotations

import asyncio
import errno
import json
import socket
import ssl
import time
from dataclasses import dataclass
from typing import Callable

JOIN_CHECK_S = 5.0  # a joining host with no link this long after its bus opened looks for the cause
PROBE_TIMEOUT_S = 3.0  # each probe's connect and handshake
# how long the far end must have been reachable (its handshake through) before no link means a refused sign-in:
# Zenoh tries a connect endpoint again after at most 4 s (connect/retry/period_max_ms), so a learner that has
# just come up is linked by then
SIGN_IN_GRACE_S = 5.0
CERTIFICATE_KEYS = ("root_ca_certificate", "listen_private_key", "listen_certificate", "connect_private_key",
                    "connect_certificate")


@dataclass(frozen=True)
class Cause:
    """Why ``endpoint`` gives no link: ``line`` to say; ``final``: it will not mend by waiting."""

    endpoint: str
    line: str
    final: bool = True
    reached: bool = False  # the far end answered (its handshake went through): all that is left is the sign-in


def tls_settings(config_file: str) -> dict:
    """``transport/link/tls`` of a native Zenoh config file (paths as written: Zenoh reads them from the working
    directory); empty without one."""
    if not config_file:
        return {}
    import zenoh

    value = json.loads(zenoh.Config.from_file(config_file).get_json("transport/link/tls"))
    return {k: v for k, v in value.items() if v is not None} if isinstance(value, dict) else {}


def certificate_problem(config_file: str) -> str | None:
    """A certificate or key that ``bus.config_file`` names and that cannot be read, as the config error to say."""
    try:
        settings = tls_settings(config_file)
    except Exception as exc:  # zenoh.ZError: the file does not parse (said by the endpoint check)
        return f"bus.config_file = {config_file!r}: {exc}"
    for key in CERTIFICATE_KEYS:
        path = settings.get(key)
        if not isinstance(path, str):
            continue
        try:
            with open(path, "rb") as file:
                file.read(1)
        except OSError as exc:
            why = "no such file" if isinstance(exc, FileNotFoundError) else exc.strerror or str(exc)
            return f"bus.config_file = {config_file!r}: transport.link.tls.{key} = {path!r}: {why}"
    return None


def split_endpoint(endpoint: str) -> tuple[str, str, int] | None:
    """``("tls", "192.0.2.1", 7447)`` of ``tls/192.0.2.1:7447`` (Zenoh's metadata after ``?`` or ``#`` left
    out); None for an endpoint that is not an address and port."""
    proto, _, address = endpoint.partition("/")
    address = address.split("?")[0].split("#")[0]
    host, _, port = address.rpartition(":")
    if not host or not port.isdigit():
        return None
    return proto, host.strip("[]"), int(port)


def tls_context(settings: dict) -> tuple[ssl.SSLContext, str]:
    """A client context as Zenoh's TLS link would check the far end, and the CA it checks against, in words."""
    context = ssl.SSLContext(ssl.PROTOCOL_TLS_CLIENT)
    ca = settings.get("root_ca_certificate")
    if ca:
        context.load_verify_locations(cafile=ca)
        against = f"the CA in root_ca_certificate = {ca!r}"
    else:
        context.load_default_certs()
        against = "the system's CAs (bus.config_file names no root_ca_certificate)"
    context.check_hostname = settings.get("verify_name_on_connect", True) is not False
    if settings.get("enable_mtls") and settings.get("connect_certificate") and settings.get("connect_private_key"):
        context.load_cert_chain(settings["connect_certificate"], settings["connect_private_key"])
    return context, against


def diagnose(endpoint: str, config_file: str = "", secret_file: str = "", run: str = "",
             timeout: float = PROBE_TIMEOUT_S) -> Cause:
    """Why this host has no link to ``endpoint`` (blocking: at most about ``2 * timeout`` seconds)."""
    parts = split_endpoint(endpoint)
    if parts is None:
        return Cause(endpoint, f"no link to {endpoint} (not an address EBRL can look into; Zenoh's own log says why: "
                               "RUST_LOG=debug)")
    proto, host, port = parts
    try:
        sock = socket.create_connection((host, port), timeout=timeout)
    except socket.gaierror as exc:
        return Cause(endpoint, f"{endpoint}: the name {host!r} does not resolve ({exc.strerror})")
    except ConnectionRefusedError:
        return Cause(endpoint, f"nothing listens at {endpoint} yet (is the learner's `ebrl up` started, with this "
                               "address in its listen?)", final=False)
    except (socket.timeout, TimeoutError):
        return Cause(endpoint, f"no answer from {endpoint} within {timeout:g} s (no route to it: a wrong address, a "
                               "firewall, or its machine is down)")
    except OSError as exc:
        if exc.errno in (errno.EHOSTUNREACH, errno.ENETUNREACH, errno.EADDRNOTAVAIL):
            return Cause(endpoint, f"no route to {endpoint} from this host ({exc.strerror})")
        return Cause(endpoint, f"cannot reach {endpoint}: {exc.strerror or exc}")
    with sock:
        if proto == "tls":
            settings = tls_settings(config_file)
            try:
                context, against = tls_context(settings)
            except (OSError, ssl.SSLError) as exc:
                return Cause(endpoint, f"bus.config_file = {config_file!r}: its TLS files do not load ({exc})")
            sock.settimeout(timeout)
            try:
                with context.wrap_socket(sock, server_hostname=host):
                    pass
            except ssl.SSLCertVerificationError as exc:
                return Cause(endpoint, f"the TLS handshake with {endpoint} failed: its certificate does not verify "
                                       f"against {against}: {exc.verify_message}")
            except (ssl.SSLError, OSError) as exc:
                return Cause(endpoint, f"the TLS handshake with {endpoint} failed: {getattr(exc, 'reason', None) or exc}"
                                       " (is it a tls/ endpoint? do both sides' certificates match bus.config_file?)")
    if secret_file:
        return Cause(endpoint, f"{endpoint} refused this host's sign-in: bus.secret_file = {secret_file!r} is not the "
                               f"secret of run {run!r} there (copy the primary host's file here, mode 0600)",
                     reached=True)
    return Cause(endpoint, f"{endpoint} answers, but no Zenoh session formed with it (is it a launcher or an `ebrl "
                           "router` of this run, with bus.auth as here? Zenoh's own log says more: RUST_LOG=debug)",
                 reached=True)


async def await_link(linked: Callable[[], bool], endpoints: list[str], probe: Callable[[str], Cause],
                     say: Callable[[str], None], patience_s: float, check_after_s: float = JOIN_CHECK_S,
                     grace_s: float = SIGN_IN_GRACE_S) -> str | None:
    """Wait until ``linked()``; None once it is. Where it is not after ``check_after_s``, ``probe`` each endpoint
    (in a thread: it blocks): a cause that will not mend on every endpoint is returned as the line to stop with;
    an endpoint where nothing listens yet is said once and waited for, until ``patience_s`` in all (then its
    cause is returned). An endpoint that answers without a link is a refused sign-in only once it has answered
    for ``grace_s`` (Zenoh's next try would have linked a learner that had just come up)."""
    start = time.monotonic()
    next_check, waiting_said = start + check_after_s, False
    reached_at: dict[str, float] = {}
    while not linked():
        now = time.monotonic()
        if now >= next_check:
            causes = await asyncio.to_thread(lambda: [probe(endpoint) for endpoint in endpoints])
            if linked():
                return None
            now = time.monotonic()
            for cause in causes:  # since when each endpoint answers
                if cause.reached:
                    reached_at.setdefault(cause.endpoint, now)
                else:
                    reached_at.pop(cause.endpoint, None)
            final = [c.final and (not c.reached or now - reached_at[c.endpoint] >= grace_s) for c in causes]
            if all(final) or now - start >= patience_s:
                return "; ".join(cause.line for cause in causes)
            if not waiting_said and (absent := [c.line for c in causes if not c.final]):
                say("; ".join(absent) + f"; waiting for it (at most run.startup_timeout = {patience_s:g} s)")
                waiting_said = True
            next_check = now + 1.0
        await asyncio.sleep(0.1)
    return None
