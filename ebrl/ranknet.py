"""The network that training ranks on several hosts use (``train.rendezvous``, ``train.trusted_networks``).

torch.distributed's channel (its TCP store, gloo's and NCCL's connections) has no authentication and no
encryption, and rank 0's store listens on every interface of its host. So ranks on several hosts meet only on
networks the user declares trusted: the rendezvous address must lie inside one, and each host connects its ranks
over its interface there (``GLOO_SOCKET_IFNAME``, ``NCCL_SOCKET_IFNAME``); a host with no such interface, or a
rendezvous outside them, is refused before anything starts (:func:`across_hosts`).
"""

from __future__ import annotations

import ipaddress
import socket

from ebrl.config import Config
from ebrl.hosts import HostPlan


def networks(cfg: Config) -> list[ipaddress.IPv4Network | ipaddress.IPv6Network]:
    return [ipaddress.ip_network(n, strict=False) for n in cfg.train.trusted_networks]


def interfaces() -> dict[str, list[str]]:
    """This host's network interfaces and their IP addresses."""
    import psutil

    return {name: [a.address.split("%")[0] for a in addrs if a.family in (socket.AF_INET, socket.AF_INET6)]
            for name, addrs in psutil.net_if_addrs().items()}


def resolve(rendezvous: str) -> tuple[str, int]:
    """``(address, port)`` of ``HOST:PORT``; ValueError where HOST does not resolve."""
    host, _, port = rendezvous.rpartition(":")
    host = host.strip("[]")
    try:
        return socket.getaddrinfo(host, int(port), proto=socket.IPPROTO_TCP)[0][4][0], int(port)
    except (socket.gaierror, ValueError) as exc:
        raise ValueError(f"train.rendezvous = {rendezvous!r}: {host!r} does not resolve ({exc})") from None


def across_hosts(cfg: Config, plan: HostPlan, found: dict[str, list[str]] | None = None) -> tuple[str, str] | None:
    """Where this host's training ranks meet the others' and over which interface: ``(HOST:PORT, interface)``;
    None where ranks do not span hosts (or this host runs none). ValueError with the reason where the config's
    networks do not allow it (``found``: this host's interfaces, :func:`interfaces` by default)."""
    if not (plan.ranks_elsewhere and "train" in plan.roles):
        return None
    trusted = networks(cfg)
    address, port = resolve(cfg.train.rendezvous)
    if not any(ipaddress.ip_address(address) in net for net in trusted):
        raise ValueError(f"train.rendezvous = {cfg.train.rendezvous!r} ({address}) is outside train.trusted_networks "
                         f"({', '.join(cfg.train.trusted_networks)}): the ranks' channel has no authentication or "
                         "encryption of its own, so it runs only on a network declared trusted")
    found = interfaces() if found is None else found
    inside = [(name, a) for name, addrs in found.items() for a in addrs
              if any(ipaddress.ip_address(a) in net for net in trusted)]
    if not inside:
        raise ValueError(f"training ranks on host {plan.name or plan.instance}: none of its addresses is in "
                         f"train.trusted_networks ({', '.join(cfg.train.trusted_networks)}): "
                         + "; ".join(f"{n}: {', '.join(a) or '-'}" for n, a in found.items()))
    if plan.primary and address not in {a for addrs in found.values() for a in addrs}:
        raise ValueError(f"train.rendezvous = {cfg.train.rendezvous!r}: {address} is not an address of this host, "
                         "the primary (rank 0 holds the ranks' meeting point)")
    return f"{address}:{port}" if ":" not in address else f"[{address}]:{port}", inside[0][0]
