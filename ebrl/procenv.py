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


def service_env(*, local_sim: bool | None = None, dist_addr: str | None = None,
                version_floor: int | None = None) -> dict[str, str]:
    """The EBRL variables for one service process (only those that apply to it)."""
    env: dict[str, str] = {}
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
