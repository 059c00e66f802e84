"""Data-parallel training with torch.distributed (``train.world_size`` > 1).

The ranks are ``train/0 .. train/<world_size - 1>``, one process each, in one
gloo process group whose address the launcher hands out
(``EBRL_DIST_ADDR``). Rank 0 is the train service the rest of the run sees: it
alone receives trajectories, publishes weights and writes checkpoints. For each
update it takes a batch, cuts it into ``world_size`` shards of about equal
decisions and scatters them (a torch.distributed collective: the ranks are one
job, the bus is for the stages). Every rank builds its shard's batch (GAE with
the same critic) and runs the same number of minibatch steps through
``DistributedDataParallel``, whose backward all-reduces the gradients, so all
ranks hold the same weights after every step.

Rank 0 sends a command every ``KEEPALIVE_S`` while it waits for data and a stop
at the end, so the other ranks never block on a collective for long, and a dead
rank surfaces as a collective error within ``TIMEOUT_S`` (its process exits; the
launcher restarts the whole group).
"""

from __future__ import annotations

import datetime
import os
from dataclasses import dataclass
from typing import Any, Callable, Sequence

import torch
import torch.distributed as dist
from torch import nn

ADDR_VAR = "EBRL_DIST_ADDR"  # host:port of rank 0's rendezvous store, set by the launcher
KEEPALIVE_S = 1.0
TIMEOUT_S = 60.0


class Methods(nn.Module):
    """Calls a method of the policy through ``forward``: DDP only synchronises what goes through forward,
    and PPO needs ``evaluate``."""

    def __init__(self, policy: nn.Module):
        super().__init__()
        self.policy = policy

    def forward(self, method: str, *args: Any) -> Any:
        return getattr(self.policy, method)(*args)


@dataclass
class Command:
    kind: str  # "update" (with this rank's shard), "idle" (keep-alive) or "stop"
    items: list | None = None


def shards(items: Sequence, size: Callable[[Any], int], world: int) -> list[list]:
    """Cut ``items`` (in order) into ``world`` runs of about equal total ``size``; a run may be empty when
    there are fewer items than ranks."""
    total = sum(size(item) for item in items)
    out: list[list] = [[] for _ in range(world)]
    done = 0
    for item in items:
        rank = min(world - 1, done * world // max(total, 1))
        out[rank].append(item)
        done += size(item)
    return out


class DataParallel:
    """One rank's membership of the training group."""

    def __init__(self, policy: nn.Module, rank: int, world: int, address: str | None = None):
        address = address or os.environ.get(ADDR_VAR, "")
        if not address:
            raise RuntimeError(f"train.world_size = {world}: {ADDR_VAR} (rank 0's host:port) is not set; "
                               "start training ranks with `ebrl up`")
        self.rank, self.world = rank, world
        dist.init_process_group("gloo", init_method=f"tcp://{address}", rank=rank, world_size=world,
                                timeout=datetime.timedelta(seconds=TIMEOUT_S))
        # broadcast_buffers=False: forward passes must not be collectives (ranks call value() a different
        # number of times); the policies keep no buffers that change.
        self.net = nn.parallel.DistributedDataParallel(Methods(policy), broadcast_buffers=False)

    def send(self, command: Command | list[Command]) -> Command:
        """Rank 0: scatter one command per rank (or the same to all); return rank 0's own."""
        commands = command if isinstance(command, list) else [command] * self.world
        mine: list[Any] = [None]
        dist.scatter_object_list(mine, commands, src=0)
        return mine[0]

    def receive(self) -> Command:
        """Ranks > 0: wait for rank 0's next command."""
        mine: list[Any] = [None]
        dist.scatter_object_list(mine, None, src=0)
        return mine[0]

    def close(self) -> None:
        if dist.is_initialized():
            dist.destroy_process_group()
