"""The environment the launcher hands to the services it starts: EBRL's whole launcher↔service contract.

Everything else a service needs comes from its command line (``--config``, ``--instance``,
``--connect``) and the bus. GPU placement travels in CUDA's own variables
(``CUDA_VISIBLE_DEVICES``, ``CUDA_MPS_*``), built by ``ebrl.resources.pool.Binding.env``.
"""

from __future__ import annotations

import os
from typing import Mapping

LOCAL_SIM = "EBRL_LOCAL_SIM"  # "0": the allocator's host runs no simulator (multi-host runs)
DIST_ADDR = "EBRL_DIST_ADDR"  # the training ranks' rendezvous (train.world_size > 1): file://RUN_DIR/.dist-... or host:port
VERSION_FLOOR = "EBRL_VERSION_FLOOR"  # newest policy version published before a train restart
IDENTITY = "EBRL_BUS_IDENTITY"  # user:password of the process's own instance identity (ebrl.bus.auth)
SIM_HOSTS = "EBRL_SIM_HOSTS"  # the run's simulator hosts, "0" or "1,2"; unset: any its launchers admit


def service_env(*, local_sim: bool | None = None, dist_addr: str | None = None,
                version_floor: int | None = None, identity: str | None = None,
                sim_hosts: tuple[int, ...] | None = None) -> dict[str, str]:
    """The EBRL variables for one service process (only those that apply to it)."""
    env: dict[str, str] = {}
    if identity:
        env[IDENTITY] = identity
    if sim_hosts is not None:
        env[SIM_HOSTS] = ",".join(str(h) for h in sim_hosts)
    if local_sim is not None:
        env[LOCAL_SIM] = "1" if local_sim else "0"
    if dist_addr:
        env[DIST_ADDR] = dist_addr
    if version_floor is not None:
        env[VERSION_FLOOR] = str(version_floor)
    return env


def local_sim(environ: Mapping[str, str] = os.environ) -> bool:
    """Does this host run a simulator (the default when no launcher said otherwise)?"""
    return environ.get(LOCAL_SIM, "1") == "1"


def dist_addr(environ: Mapping[str, str] = os.environ) -> str:
    return environ.get(DIST_ADDR, "")


def version_floor(environ: Mapping[str, str] = os.environ) -> int:
    """The newest version anyone saw before this train, gen or eval was started again (-1: none; a fresh
    start)."""
    return int(environ.get(VERSION_FLOOR, "-1"))


def take_identity(environ: "os._Environ[str] | dict[str, str]" = os.environ) -> str:
    """This process's instance identity (``user:password``; empty when its launcher gave none: a mesh, an open
    bus, a service started by hand), removed from the environment as it is read, so that what the service
    starts (env workers running the user's env code, their children) does not inherit it."""
    return environ.pop(IDENTITY, "")


def sim_hosts(environ: Mapping[str, str] = os.environ) -> frozenset[int] | None:
    """The simulator hosts the run has (its launcher's plan), or None where no launcher said (services started
    in one process by a test or a script; a run whose hosts join with ``--only``: any host a launcher admits)."""
    text = environ.get(SIM_HOSTS)
    if text is None:
        return None
    return frozenset(int(h) for h in text.split(",") if h.strip().isdigit())
