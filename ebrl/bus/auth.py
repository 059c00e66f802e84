"""Who may join a run's bus: the run's secret, and the endpoints that need TLS.

Each run has a secret file, ``RUN_DIR/bus.secret`` (mode 0600, created by the launcher; ``bus.secret_file``
names a shared one for a run over several hosts). It is a Zenoh user-password dictionary of two users::

    ebrl:<64 hex digits>
    observer:<64 hex digits>

* Every service of the run, and its launcher, signs in as ``ebrl`` and checks whoever connects against the
  file (Zenoh's ``transport/auth/usrpwd``). A process that does not hold the file cannot open a session with
  any of them: nothing it sends arrives, and it receives nothing.
* A script that watches the run (``ebrl stats``, ``ebrl bench``, ``examples/subscribe_stats.py``) signs in as
  ``observer``, as a Zenoh client of the launcher. Zenoh's access control on every service drops what an
  observer publishes (puts, deletes, queryables, liveliness tokens): it reads, it cannot act on the run.
  (The file holds the service password too: it is the owner's, 0600, like the processes they could as well
  signal.)

Signing in does not encrypt the session: on loopback that is enough; between hosts the endpoints must be TLS
(:func:`check_endpoints`).
"""

from __future__ import annotations

import ipaddress
import os
import secrets
import stat
from dataclasses import dataclass
from pathlib import Path
from typing import Literal

FILENAME = "bus.secret"
SERVICE_USER = "ebrl"
OBSERVER_USER = "observer"
Role = Literal["service", "observer"]


class AuthError(ValueError):
    """A secret file that is missing, unreadable, malformed or readable by others."""


@dataclass(frozen=True)
class Credentials:
    user: str
    password: str
    path: Path  # the dictionary file every service checks peers against


def create(path: str | os.PathLike) -> Path:
    """Write a new secret file at ``path`` (0600, fsynced); an existing file is an error, never replaced."""
    path = Path(path)
    lines = "".join(f"{user}:{secrets.token_hex(32)}\n" for user in (SERVICE_USER, OBSERVER_USER))
    fd = os.open(path, os.O_WRONLY | os.O_CREAT | os.O_EXCL, 0o600)
    try:
        os.write(fd, lines.encode())
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
    secrets existed); an existing one is checked (:func:`load`)."""
    path = Path(path)
    if not path.exists():
        try:
            return create(path)
        except FileExistsError:  # created meanwhile by another launcher of this run
            pass
    load(path, "service")
    return path


def load(path: str | os.PathLike, role: Role) -> Credentials:
    """The credentials ``role`` signs in with, from the secret file at ``path``."""
    path = Path(path)
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
    user = SERVICE_USER if role == "service" else OBSERVER_USER
    if user not in users:
        raise AuthError(f"bus secret {path} has no {user!r} line")
    return Credentials(user=user, password=users[user], path=path.resolve())


# What a service takes from an observer: nothing that would act on the run. It may subscribe (to
# ebrl/stats/** or anything else its owner could read anyway) and query; every put, delete, queryable and
# liveliness token it sends is dropped where it enters (Zenoh's access control, on the user name).
OBSERVER_DENIED = ["put", "delete", "declare_queryable", "liveliness_token"]


def access_control() -> dict[str, object]:
    """The ``access_control`` block of every service: observers may read, never publish."""
    return {
        "enabled": True,
        "default_permission": "allow",
        "rules": [{"id": "observers-read-only", "permission": "deny", "flows": ["ingress"],
                   "messages": OBSERVER_DENIED, "key_exprs": ["**"]}],
        "subjects": [{"id": "observers", "usernames": [OBSERVER_USER]}],
        "policies": [{"rules": ["observers-read-only"], "subjects": ["observers"]}],
    }


def zenoh_settings(credentials: Credentials, role: Role) -> dict[str, object]:
    """Zenoh config entries (path -> value) for a session of ``role``: sign in with ``credentials``; a service
    also checks whoever connects against the file, and takes nothing but subscriptions and queries from an
    observer (:func:`access_control`)."""
    usrpwd: dict[str, str] = {"user": credentials.user, "password": credentials.password}
    if role == "service":
        usrpwd["dictionary_file"] = str(credentials.path)
        return {"transport/auth/usrpwd": usrpwd, "access_control": access_control()}
    return {"transport/auth/usrpwd": usrpwd}


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
