"""Bus endpoints on this host: a free TCP port, and a listen endpoint that falls back to one."""

from __future__ import annotations

import socket
import sys


def free_port(host: str = "127.0.0.1") -> int:
    with socket.socket() as sock:
        sock.bind((host, 0))
        return sock.getsockname()[1]


def listen_endpoint(wanted: str, strict: bool = False) -> str:
    """``wanted`` if its TCP port is free, else the same host on a free port (logged); ``strict`` (other
    hosts will connect to it) raises OSError instead."""
    proto, _, address = wanted.partition("/")
    host, _, port = address.rpartition(":")
    if proto != "tcp" or not port.isdigit():
        return wanted
    with socket.socket() as sock:
        sock.setsockopt(socket.SOL_SOCKET, socket.SO_REUSEADDR, 1)  # as Zenoh's listener: TIME_WAIT is no conflict
        try:
            sock.bind((host.strip("[]"), int(port)))
            return wanted
        except OSError:
            if strict:
                raise OSError(f"cannot listen on {wanted}: the port is busy or the address is not this host's")
            sock.bind((host.strip("[]"), 0))
            free = f"tcp/{host}:{sock.getsockname()[1]}"
    print(f"ebrl: {wanted} is busy (another run?); listening on {free} instead", file=sys.stderr)
    return free


def address_in_use(exc: BaseException) -> bool:
    """Whether a failed bind (Zenoh's error, or the OS's) says the address is already in use."""
    import errno

    return getattr(exc, "errno", None) == errno.EADDRINUSE or "Address already in use" in str(exc)


def _file_setting(config_file: str, path: str) -> object:
    """What a native Zenoh config file sets at ``path`` (JSON), or None where it leaves Zenoh's default."""
    import json

    import zenoh

    value = json.loads(zenoh.Config.from_file(config_file).get_json(path))
    return None if value == json.loads(zenoh.Config().get_json(path)) else value


def _endpoints(value: object) -> list[str]:
    """Endpoints as a config gives them: a list, or lists per mode (``{"router": [...], "peer": [...]}``)."""
    lists = value.values() if isinstance(value, dict) else [value]
    return [e for endpoints in lists if isinstance(endpoints, list) for e in endpoints if isinstance(e, str)]


def config_file_endpoints(config_file: str) -> list[str]:
    """Every endpoint a native Zenoh config file sets for a session to use: its listen and its connect ones."""
    return config_file_listen(config_file) + config_file_connect(config_file)


def config_file_connect(config_file: str) -> list[str]:
    """The connect endpoints a native Zenoh config file sets."""
    return _endpoints(_file_setting(config_file, "connect/endpoints")) if config_file else []


def config_file_acl(config_file: str) -> bool:
    """Whether a native Zenoh config file turns on access control of its own."""
    return bool(config_file) and bool(_file_setting(config_file, "access_control/enabled"))


def config_file_listen(config_file: str) -> list[str]:
    """The listen endpoints a native Zenoh config file sets (they are never replaced by EBRL's); none where it
    leaves Zenoh's default (which listens on every interface)."""
    if not config_file:
        return []
    return _endpoints(_file_setting(config_file, "listen/endpoints"))
