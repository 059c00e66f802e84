"""Who may join a run's bus and what each may send: the run's secret, one identity per role, and the endpoints
that need TLS.

Each run has a secret file, ``RUN_DIR/bus.secret`` (mode 0600, created by the launcher; ``bus.secret_file``
names a shared one for a run over several hosts). It is a Zenoh user-password dictionary with one line per
identity: one per role of the service graph (``ebrl-sim``, ``ebrl-gen``, ``ebrl-train``, ``ebrl-eval``,
``ebrl-alloc``, ``ebrl-log``, ``ebrl-viz``, ``ebrl-launcher``) and ``observer``::

    ebrl-sim:<64 hex digits>
    ...
    observer:<64 hex digits>

* With ``bus.mode = "client"`` (the default) every service is a client of its host's launcher, a Zenoh router
  that checks each one's sign-in against the file and takes from it only what its role's flows declare
  (:func:`ebrl.graph.access_control`, default deny): sim's credential cannot publish weights, stops, quotas,
  GPU shares or train's stats. Zenoh's user-password sign-in identifies only the side of a link that connects,
  so rights hold where every sender connects to the one that checks: the router. Launchers of other hosts sign
  in as ``ebrl-launcher`` (they route every role's traffic, checked at their own host); the link a launcher
  opens itself (``bus.connect``) is trusted by the Zenoh id of the launcher or router at its far end, which
  only holders of the launcher's password can compute (:func:`host_zid`). That far end must be a launcher that
  opens no link itself (the primary host, say) or an ``ebrl router``: those have the computed ids.
* With ``bus.mode = "peer"`` services talk directly; each still signs in as its role and checks whoever
  connects, but rights per role cannot hold on a mesh: services trust each other, and observers only read.
* A process that does not hold a line of the file cannot open a session with any of them: nothing it sends
  arrives, and it receives nothing.
* Each process the launcher starts (``bus.mode = "client"``) signs in with an identity of its own instance,
  ``ebrl-<role>-<n>`` (:func:`instance_user`), whose password is derived from the launcher's
  (:func:`instance_password`): the launcher hands each child its line alone (``ebrl.procenv``), and its router
  admits exactly the instances it started (:func:`write_router_dictionary`), each taking only its own
  instance's keys (its token, stats, status and control: ``ebrl.graph.access_control``). A process holding
  sim/0's line cannot compute sim/1's, nor hold ``ebrl/live/<run>/sim/1``. The role lines of the services
  are for a mesh (``bus.mode = "peer"``); a client-mode launcher does not admit them.
* A script that watches the run (``ebrl stats``, ``ebrl bench``, ``examples/subscribe_stats.py``) signs in as
  ``observer``: it may read the run's stats and nothing else. ``ebrl secret --observer`` writes a file with that
  line alone, to hand to another user.

Signing in does not encrypt the session: on loopback that is enough; between hosts the endpoints must be TLS
(:func:`check_endpoints`).
"""

from __future__ import annotations

import hashlib
import hmac
import ipaddress
import os
import secrets
import stat
from dataclasses import dataclass
from pathlib import Path

from ebrl import durable, graph

FILENAME = "bus.secret"
OBSERVER_USER = graph.username("observer")
IDENTITIES = tuple(graph.FLOWS)  # the roles that sign in: every role of the service graph, observer included


class AuthError(ValueError):
    """A secret file that is missing, unreadable, malformed or readable by others."""


@dataclass(frozen=True)
class Credentials:
    user: str
    password: str
    path: Path | None  # the dictionary file every service checks peers against (None: an instance's line alone)


def _new_lines(users) -> str:
    return "".join(f"{user}:{secrets.token_hex(32)}\n" for user in users)


def create(path: str | os.PathLike) -> Path:
    """Write a new secret file at ``path`` (0600, fsynced): a password for each identity; an existing file is an
    error, never replaced (``ebrl.durable``)."""
    return durable.write_text(path, _new_lines(graph.username(role) for role in IDENTITIES), mode=0o600,
                              exclusive=True)


def write_observer(secret: str | os.PathLike, path: str | os.PathLike) -> Path:
    """Write at ``path`` (0600, fsynced; an existing file is never replaced) the observer's line of the run's
    secret file ``secret`` alone: what another user or a script needs to watch the run (read its stats, ask a
    service's status) and nothing more. It holds no service password, so it cannot sign in as a service."""
    credentials = load(secret, "observer")
    return durable.write_text(path, f"{credentials.user}:{credentials.password}\n", mode=0o600, exclusive=True)


def ensure(path: str | os.PathLike) -> Path:
    """The secret file at ``path``, created when there is none (a new run, or a run resumed from before
    secrets existed); an existing one is checked (:func:`load`), and one made before identities per role (a
    resumed run's) gets the identities it lacks, appended and fsynced (its lines are kept)."""
    path = Path(path)
    if not path.exists():
        try:
            return create(path)
        except FileExistsError:  # created meanwhile by another launcher of this run
            pass
    users = _users(path)
    missing = [graph.username(role) for role in IDENTITIES if graph.username(role) not in users]
    if missing:
        with open(path, "a") as file:
            file.write(_new_lines(missing))
            file.flush()
            os.fsync(file.fileno())
    load(path, "launcher")
    return path


def _users(path: Path) -> dict[str, str]:
    """The user -> password lines of the secret file at ``path``, checked: private, well formed."""
    try:
        info = path.stat()
        text = path.read_text()
    except OSError as exc:
        raise AuthError(f"bus secret {path}: {exc.strerror or exc} (the run's launcher creates it; "
                        "a script watching a run needs read access to it)") from None
    if info.st_mode & (stat.S_IRWXG | stat.S_IRWXO):
        raise AuthError(f"bus secret {path} is open to other users (mode {stat.S_IMODE(info.st_mode):04o}): "
                        f"chmod 600 {path}")
    users: dict[str, str] = {}
    for number, line in enumerate(text.splitlines(), 1):
        user, sep, password = line.strip().partition(":")
        if line.strip() and (not sep or not user or len(password) < 16):
            raise AuthError(f"bus secret {path}, line {number}: expected USER:PASSWORD (16 characters or more)")
        if sep:
            users[user] = password
    return users


def load(path: str | os.PathLike, role: str) -> Credentials:
    """The credentials ``role`` (a role of the service graph, or ``observer``) signs in with, from the secret
    file at ``path``."""
    path = Path(path)
    if role not in IDENTITIES:
        raise AuthError(f"no identity for {role!r}: identities are {', '.join(IDENTITIES)}")
    users, user = _users(path), graph.username(role)
    if user not in users:
        fix = "" if role == "observer" else (" (a file made before identities per role, or an observer's file: "
                                             "make a new one with `ebrl secret PATH`)")
        raise AuthError(f"bus secret {path} has no {user!r} line{fix}")
    return Credentials(user=user, password=users[user], path=path.resolve())


def host_zid(secret: str | os.PathLike, host: int | str) -> str:
    """The Zenoh id of host ``host``'s launcher (a number) or of ``ebrl router`` (``"router"``): derived from the
    launcher's password, so every launcher of the run can tell the router at the end of the link it opened,
    and a holder of another role's line cannot compute it (32 hex digits, no leading zero, as Zenoh wants)."""
    key = load(secret, "launcher").password.encode()
    digest = hmac.new(key, f"ebrl-zid:{host}".encode(), hashlib.sha256).hexdigest()[:32]
    return ("1" + digest[1:]) if digest[0] == "0" else digest


# --- identities per instance -----------------------------------------------------------------------------------

ROUTER_FILE = "bus.router-{host}.secret"  # in the run's directory: the dictionary a client-mode launcher admits


def instance_user(role: str, instance: int) -> str:
    """The Zenoh user name of service instance ``role/instance``: ``ebrl-<role>-<instance>``."""
    if role not in graph.SERVICES or int(instance) < 0:
        raise AuthError(f"no instance identity for {role}/{instance}: roles are {', '.join(graph.SERVICES)}")
    return graph.instance_username(role, instance)


def instance_password(secret: str | os.PathLike, role: str, instance: int) -> str:
    """The password of ``role/instance``'s identity: an HMAC of its user name under the launcher's password, so
    the launcher (and every launcher of the run, which shares the secret) can make it, and a holder of another
    instance's line, or of a role's line, cannot (64 hex digits)."""
    key = load(secret, "launcher").password.encode()
    return hmac.new(key, f"ebrl-instance:{instance_user(role, instance)}".encode(), hashlib.sha256).hexdigest()


def instance_line(secret: str | os.PathLike, role: str, instance: int) -> str:
    """``user:password`` of ``role/instance``: what the launcher hands that process (``ebrl.procenv``)."""
    return f"{instance_user(role, instance)}:{instance_password(secret, role, instance)}"


def parse_line(line: str) -> Credentials:
    """The credentials of one ``user:password`` line (an instance's, as the launcher hands it over)."""
    user, sep, password = line.strip().partition(":")
    if not sep or not user or len(password) < 16:
        raise AuthError("a bus identity is USER:PASSWORD (16 characters or more)")
    return Credentials(user=user, password=password, path=None)


def instance_of(user: str) -> tuple[str, int] | None:
    """``(role, instance)`` of an instance identity's user name, None for any other (a role's, observer)."""
    prefix, _, number = user.rpartition("-")
    role = prefix.removeprefix("ebrl-")
    if not prefix.startswith("ebrl-") or role not in graph.SERVICES or not number.isdigit():
        return None
    return role, int(number)


def write_router_dictionary(secret: str | os.PathLike, path: str | os.PathLike,
                            instances: list[tuple[str, int]] | tuple[tuple[str, int], ...]) -> Path:
    """Write at ``path`` (0600, fsynced, replacing any older one at once) the user-password dictionary of a
    client-mode launcher's router: the launcher's and the observer's lines of ``secret`` (other hosts'
    launchers, scripts watching) and one line per service instance of ``instances`` it starts. The services'
    role lines are left out: no process it starts signs in with one. Derived from ``secret`` alone, so written
    anew at each start."""
    path = Path(path)
    users = _users(Path(secret))
    lines = [f"{user}:{users[user]}" for user in (graph.username("launcher"), OBSERVER_USER) if user in users]
    lines += [instance_line(secret, role, instance) for role, instance in instances]
    return durable.write_text(path, "".join(line + "\n" for line in lines), mode=0o600)


TRUSTED_HOSTS = 256  # launchers numbered below this, and the router, are trusted at the end of a link opened


# What a peer (bus.mode = "peer") takes from an observer: nothing that would act on the run. It may subscribe
# and query; every put, delete, queryable and liveliness token it sends is dropped where it enters (Zenoh's
# access control, on the user name). Between peers, services trust each other.
OBSERVER_DENIED = ["put", "delete", "declare_queryable", "liveliness_token"]


def peer_access_control() -> dict[str, object]:
    """The ``access_control`` block of every peer of a mesh: observers may read, never publish."""
    return {
        "enabled": True,
        "default_permission": "allow",
        "rules": [{"id": "observers-read-only", "permission": "deny", "flows": ["ingress"],
                   "messages": OBSERVER_DENIED, "key_exprs": ["**"]}],
        "subjects": [{"id": "observers", "usernames": [OBSERVER_USER]}],
        "policies": [{"rules": ["observers-read-only"], "subjects": ["observers"]}],
    }


def zenoh_settings(credentials: Credentials, mode: str, run: str = "*", connects: bool = False,
                   instances: tuple[tuple[str, int], ...] = (), dictionary: str | os.PathLike | None = None,
                   groups: int = 0, planned: tuple[tuple[str, int], ...] | None = None,
                   shares: tuple[tuple[tuple[str, int], ...], ...] = ()) -> dict[str, object]:
    """Zenoh config entries (path -> value) for a session that signs in with ``credentials``, of Zenoh
    ``mode``:

    * ``router`` (a launcher, ``ebrl router``): checks whoever connects against the file and takes from each
      identity only what its role declares in run ``run`` (:func:`ebrl.graph.access_control`); ``connects``:
      it opens links itself (``bus.connect``), whose far ends are trusted by their Zenoh ids (:func:`host_zid`;
      one that opens none takes its own host's id: ``ebrl.bus.options.zenoh_config``). With ``instances`` (a
      client-mode launcher: the service instances it starts), it checks sign-ins against ``dictionary``
      (:func:`write_router_dictionary`) instead, and each instance takes only its own instance's keys (and,
      with ``groups`` per simulator, a simulator its own groups' data keys); with ``planned`` (every instance of
      the run), the tokens of instances the run does not have reach this router alone, to be counted; with
      ``shares`` (processes of several services, ``run.processes``), the first service's identity sends for all.
    * ``peer`` (a service of a mesh): checks whoever connects; observers only read.
    * ``client`` (a service of a launcher's, a script watching): signs in, nothing more.
    """
    usrpwd: dict[str, str] = {"user": credentials.user, "password": credentials.password}
    if mode == "client":
        return {"transport/auth/usrpwd": usrpwd}
    if credentials.path is None:
        raise AuthError(f"a {mode} checks others against the run's secret file: an instance's line alone cannot")
    usrpwd["dictionary_file"] = str(Path(dictionary).resolve() if dictionary else credentials.path)
    if instances and (mode != "router" or not dictionary):
        raise AuthError("identities per instance are admitted by a router with its own dictionary file")
    if mode == "peer":
        return {"transport/auth/usrpwd": usrpwd, "access_control": peer_access_control()}
    trusted = ([host_zid(credentials.path, h) for h in range(TRUSTED_HOSTS)]
               + [host_zid(credentials.path, "router")]) if connects else []
    return {"transport/auth/usrpwd": usrpwd, "access_control": graph.access_control(
        run, trusted_zids=trusted, instances=instances, groups=groups, planned=planned, shares=shares)}


# --- endpoints ---------------------------------------------------------------------------------------------

_ENCRYPTED = ("tls", "quic")
_LOCAL_ONLY = ("unixsock-stream", "unixpipe", "vsock")


def is_loopback(endpoint: str) -> bool:
    """Whether a Zenoh endpoint (``proto/address[?params][#config]``) stays on this host."""
    proto, _, address = endpoint.partition("/")
    if proto in _LOCAL_ONLY:
        return True
    host = address.split("#", 1)[0].split("?", 1)[0].rsplit(":", 1)[0].strip("[]").lower()
    if host == "localhost":
        return True
    try:  # an address, not a prefix: "127.attacker.example" is a name that resolves anywhere
        return ipaddress.ip_address(host).is_loopback
    except ValueError:
        return False


def insecure_endpoints(endpoints: list[str]) -> list[str]:
    """The endpoints that reach beyond this host without encryption."""
    return [e for e in endpoints if not is_loopback(e) and e.partition("/")[0] not in _ENCRYPTED]


def check_endpoints(endpoints: list[str], insecure: bool, where: str) -> str | None:
    """A message refusing plain endpoints that leave this host, or None. ``insecure``: allowed, with a warning
    (the caller prints it) — returns None then too."""
    plain = insecure_endpoints(endpoints)
    if not plain or insecure:
        return None
    return (f"{where}: {', '.join(plain)} would carry the run's data unencrypted beyond this host; use tls/... "
            "endpoints with certificates in bus.config_file (docs/scaling-out.md: \"Scaling out: several hosts, "
            "several training ranks\"), or set bus.insecure = true on a network you trust")


def secret_path(bus, run_dir: str | os.PathLike) -> str:
    """The secret file of a run from its ``[bus]`` section (``auth``, ``secret_file``) and directory; empty
    when ``bus.auth`` is off."""
    if not bus.auth:
        return ""
    return str(Path(bus.secret_file).expanduser() if bus.secret_file else Path(run_dir) / FILENAME)
