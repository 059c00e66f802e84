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

from ebrl import graph

FILENAME = "bus.secret"
OBSERVER_USER = graph.username("observer")
IDENTITIES = tuple(graph.FLOWS)  # the roles that sign in: every role of the service graph, observer included


class AuthError(ValueError):
    """A secret file that is missing, unreadable, malformed or readable by others."""


@dataclass(frozen=True)
class Credentials:
    user: str
    password: str
    path: Path  # the dictionary file every service checks peers against


def _new_lines(users) -> str:
    return "".join(f"{user}:{secrets.token_hex(32)}\n" for user in users)


def create(path: str | os.PathLike) -> Path:
    """Write a new secret file at ``path`` (0600, fsynced): a password for each identity; an existing file is an
    error, never replaced."""
    path = Path(path)
    fd = os.open(path, os.O_WRONLY | os.O_CREAT | os.O_EXCL, 0o600)
    try:
        os.write(fd, _new_lines(graph.username(role) for role in IDENTITIES).encode())
        os.fsync(fd)
    finally:
        os.close(fd)
    return path


def write_observer(secret: str | os.PathLike, path: str | os.PathLike) -> Path:
    """Write at ``path`` (0600, fsynced; an existing file is never replaced) the observer's line of the run's
    secret file ``secret`` alone: what another user or a script needs to watch the run (read its stats, ask a
    service's status) and nothing more. It holds no service password, so it cannot sign in as a service."""
    credentials = load(secret, "observer")
    fd = os.open(path, os.O_WRONLY | os.O_CREAT | os.O_EXCL, 0o600)
    try:
        os.write(fd, f"{credentials.user}:{credentials.password}\n".encode())
        os.fsync(fd)
    finally:
        os.close(fd)
    return Path(path)


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


def zenoh_settings(credentials: Credentials, mode: str, run: str = "*", connects: bool = False
                   ) -> dict[str, object]:
    """Zenoh config entries (path -> value) for a session that signs in with ``credentials``, of Zenoh
    ``mode``:

    * ``router`` (a launcher, ``ebrl router``): checks whoever connects against the file and takes from each
      identity only what its role declares in run ``run`` (:func:`ebrl.graph.access_control`); ``connects``:
      it opens links itself (``bus.connect``), whose far ends are trusted by their Zenoh ids (:func:`host_zid`;
      one that opens none takes its own host's id: ``ebrl.bus.session.zenoh_config``).
    * ``peer`` (a service of a mesh): checks whoever connects; observers only read.
    * ``client`` (a service of a launcher's, a script watching): signs in, nothing more.
    """
    usrpwd: dict[str, str] = {"user": credentials.user, "password": credentials.password}
    if mode == "client":
        return {"transport/auth/usrpwd": usrpwd}
    usrpwd["dictionary_file"] = str(credentials.path)
    if mode == "peer":
        return {"transport/auth/usrpwd": usrpwd, "access_control": peer_access_control()}
    trusted = ([host_zid(credentials.path, h) for h in range(TRUSTED_HOSTS)]
               + [host_zid(credentials.path, "router")]) if connects else []
    return {"transport/auth/usrpwd": usrpwd, "access_control": graph.access_control(run, trusted_zids=trusted)}


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
