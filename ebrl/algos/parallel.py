"""Data-parallel training with torch.distributed (``train.world_size`` > 1).

The ranks are ``train/0 .. train/<world_size - 1>``, one process each, in one
process group (NCCL when each rank has a GPU of its own, else gloo) whose address the launcher hands out
(``EBRL_DIST_ADDR``). Rank 0 is the train service the rest of the run sees: it
alone receives trajectories, publishes weights and writes checkpoints. For each
update it takes a batch, cuts it into ``world_size`` shards of about equal
decisions and scatters them (a torch.distributed collective: the ranks are one
job, the bus is for the stages). Every rank builds its shard's batch (GAE with
the same critic) and runs the same number of minibatch steps through
``DistributedDataParallel``, whose backward all-reduces the gradients, so all
ranks hold the same weights after every step. With ``train.parallel = "fsdp"``
the policy is sharded instead (``torch.distributed.fsdp.fully_shard``):
parameters, gradients and Adam's state live in 1/world_size slices, gathered
for each forward pass; the full weights are gathered for publishing after every
update and, with the optimizer state, for checkpoints. Every one of those is a
collective, so every rank makes the same calls in the same order
(``ebrl.algos.learner.Learner.learn`` and ``sync``).

Rank 0 sends a command every ``KEEPALIVE_S`` while it waits for data and a stop
at the end, so the other ranks never block on a collective for long, and a dead
rank surfaces as a collective error within ``TIMEOUT_S`` (its process exits; the
launcher restarts the whole group).
"""

from __future__ import annotations

import contextlib
import datetime
import inspect
import logging
import struct
import warnings
from dataclasses import dataclass
from typing import Any, Callable, Iterator, Protocol, Sequence

import numpy as np
import torch
import torch.distributed as dist
from torch import nn

from ebrl import procenv, typecheck
from ebrl import codec
from ebrl.messages import MessageError

log = logging.getLogger(__name__)

KEEPALIVE_S = 1.0
TIMEOUT_S = 60.0
CLOSE_BARRIER_S = 10.0  # how long a closing rank waits for the others (``DataParallel.close``)

# Newer torch (2.13 here) names it forward_sync_buffers, which still syncs buffers from rank 0 at init as it does the
# weights, and warns on every rank for broadcast_buffers; older torch (the GPU image's 2.11) knows only the latter.
_DDP_OPTIONS = inspect.signature(nn.parallel.DistributedDataParallel).parameters
_NO_FORWARD_BUFFER_SYNC = ({"forward_sync_buffers": False} if "forward_sync_buffers" in _DDP_OPTIONS
                           else {"broadcast_buffers": False})


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


COMMANDS = ("update", "idle", "stop")


class ItemWire(Protocol):
    """How a learner's items travel between ranks (its collector: ``SegmentCollector``, ``GroupCollector``)."""

    @staticmethod
    def to_wire(item: Any) -> Any: ...

    @staticmethod
    def from_wire(raw: Any) -> Any: ...


def encode_command(command: Command, wire: ItemWire) -> bytes:
    """A command as EBRL's codec writes messages (msgpack and arrays), never as a pickle."""
    items = None if command.items is None else [wire.to_wire(item) for item in command.items]
    return codec.encode({"kind": command.kind, "items": items})


def decode_command(payload: bytes, wire: ItemWire) -> Command:
    """A command from rank 0, checked as any message is (segments validated by ``ebrl.messages``)."""
    raw = codec.decode(payload)
    if (not isinstance(raw, dict) or raw.get("kind") not in COMMANDS
            or not isinstance(raw.get("items"), (list, type(None)))):
        raise MessageError(f"not a rank command: {typecheck.describe(raw)}")
    return Command(raw["kind"], None if raw["items"] is None else [wire.from_wire(item) for item in raw["items"]])


def optimizer_to_wire(state: dict) -> dict:
    """An optimizer's ``state_dict()`` as EBRL's codec carries it: tensors as arrays, tuples as lists."""
    def plain(value: Any) -> Any:
        if isinstance(value, torch.Tensor):
            return value.detach().cpu().numpy()
        if isinstance(value, (list, tuple)):
            return [plain(v) for v in value]
        if isinstance(value, dict):
            return {k: plain(v) for k, v in value.items()}
        return value
    return {"state": [[index, plain(values)] for index, values in state["state"].items()],
            "param_groups": plain(state["param_groups"])}


def optimizer_from_wire(raw: Any) -> dict:
    """:func:`optimizer_to_wire`'s dict back as ``Optimizer.load_state_dict`` takes it (checked for its shape)."""
    if not isinstance(raw, dict) or not isinstance(raw.get("state"), list) or not isinstance(raw.get("param_groups"),
                                                                                               list):
        raise MessageError(f"not an optimizer state: {typecheck.describe(raw)}")
    state = {int(index): {k: torch.from_numpy(np.array(v)) if isinstance(v, np.ndarray) else v
                          for k, v in values.items()} for index, values in raw["state"]}
    return {"state": state, "param_groups": raw["param_groups"]}


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
    """One rank's membership of the training group. ``optimizer`` is the policy's (possibly restored from a
    checkpoint); with ``shard`` it is replaced by one over the shards (``self.optimizer``), state included."""

    def __init__(self, policy: nn.Module, optimizer: torch.optim.Optimizer, rank: int, world: int,
                 address: str | None = None, shard: bool = False, device: torch.device | None = None,
                 wire: ItemWire | None = None):
        address = address or procenv.dist_addr()
        if not address:
            raise RuntimeError(f"train.world_size = {world}: {procenv.DIST_ADDR} (rank 0's host:port) is not set; "
                               "start training ranks with `ebrl up`")
        self.rank, self.world, self.shard, self.wire = rank, world, shard, wire
        self.policy, self.optimizer = policy, optimizer
        self.device = device or torch.device("cpu")
        cuda = self.device.type == "cuda"
        if cuda:
            torch.cuda.set_device(self.device)
        # NCCL wants one GPU per rank; ranks sharing a GPU (or on the CPU) use gloo
        self.backend = "nccl" if cuda and torch.cuda.device_count() >= world else "gloo"
        # "file://RUN_DIR/.dist-...": the launcher's file store; "host:port": a TCP store (tests, by hand)
        init = address if "://" in address else f"tcp://{address}"
        dist.init_process_group(self.backend, init_method=init, rank=rank, world_size=world,
                                timeout=datetime.timedelta(seconds=TIMEOUT_S))
        self._share_optimizer_state(optimizer)
        # optimizer index -> FQN; the optimizer holds the trainable parameters only (PPO.optimizer)
        self.names = [f"policy.{name}" for name, p in policy.named_parameters() if p.requires_grad]
        if not shard:
            # No buffer sync in forward: a forward pass is no collective (ranks call value() a different number
            # of times). The one buffer that changes, the observation statistics, every rank updates alike
            # from the sum over ranks (``all_sum``).
            self.net: nn.Module = nn.parallel.DistributedDataParallel(
                Methods(policy), device_ids=[self.device.index] if cuda else None, **_NO_FORWARD_BUFFER_SYNC)
            return
        from torch.distributed.checkpoint.state_dict import StateDictOptions, set_optimizer_state_dict
        from torch.distributed.fsdp import fully_shard

        with torch.no_grad():
            for tensor in policy.state_dict().values():  # every rank starts from rank 0's weights, as with DDP
                dist.broadcast(tensor, src=0)
        restored = optimizer.state_dict()
        # PPO never changes an output in place, which is what this warning is about (evaluate returns views).
        warnings.filterwarnings("ignore", message="FSDP2-wrapped module .* returned a view tensor")
        self.net = fully_shard(Methods(policy))
        self.optimizer = type(optimizer)([p for p in self.net.parameters() if p.requires_grad], **optimizer.defaults)
        if restored["state"]:
            set_optimizer_state_dict(self.net, self.optimizer, self._by_name(restored),
                                     options=StateDictOptions(full_state_dict=True))

    def _share_optimizer_state(self, optimizer: torch.optim.Optimizer) -> None:
        """Every rank takes rank 0's optimizer state (its moments and steps, restored from a checkpoint where the
        run resumed): ranks on other hosts have no checkpoint of their own, and ranks that step from different
        moments would drift apart. Sent as EBRL's codec writes it (never a pickle), over one broadcast."""
        device = self.device if self.backend == "nccl" else torch.device("cpu")
        payload = codec.encode(optimizer_to_wire(optimizer.state_dict())) if self.rank == 0 else b""
        size = torch.tensor([len(payload)], dtype=torch.int64, device=device)
        dist.broadcast(size, src=0)
        data = (torch.frombuffer(bytearray(payload), dtype=torch.uint8).to(device) if self.rank == 0
                else torch.empty(int(size.item()), dtype=torch.uint8, device=device))
        dist.broadcast(data, src=0)
        if self.rank != 0:
            optimizer.load_state_dict(optimizer_from_wire(codec.decode(data.cpu().numpy().tobytes())))

    def weights_agree(self) -> bool:
        """Whether every rank holds the same weights (DDP; sharded ones are one copy by construction): each
        tensor's sum in float64, gathered from every rank and compared exactly. A collective: every rank calls it
        after every update."""
        if self.shard:
            return True
        with torch.no_grad():
            sums = torch.stack([t.detach().double().sum() for t in self.policy.state_dict().values()])
        if self.backend != "nccl":
            sums = sums.cpu()
        gathered = [torch.empty_like(sums) for _ in range(self.world)]
        dist.all_gather(gathered, sums)
        return all(torch.equal(gathered[0], other) for other in gathered[1:])

    @contextlib.contextmanager
    def gathered(self) -> Iterator[None]:
        """Plain calls of the policy's methods (no gradients) inside; sharded: one all-gather for them."""
        if not self.shard:
            yield
            return
        self.net.unshard()
        try:
            yield
        finally:
            self.net.reshard()

    def full_arrays(self) -> dict[str, np.ndarray]:
        """The policy's weights as arrays (what Weights messages carry); sharded, a collective: rank 0 gets
        them, the others an empty dict."""
        if not self.shard:
            return {name: t.detach().cpu().numpy().copy() for name, t in self.policy.state_dict().items()}
        return {name: t.numpy() for name, t in self._full_model_state().items()}

    def checkpoint_state(self) -> tuple[dict[str, torch.Tensor], dict]:
        """(model state, optimizer state dict as ``Optimizer.state_dict`` gives it); sharded, a collective:
        complete on rank 0 only."""
        if not self.shard:
            return self.policy.state_dict(), self.optimizer.state_dict()
        from torch.distributed.checkpoint.state_dict import StateDictOptions, get_optimizer_state_dict

        model = self._full_model_state()
        optim = get_optimizer_state_dict(self.net, self.optimizer,
                                         options=StateDictOptions(full_state_dict=True, cpu_offload=True))
        return model, self._by_index(optim) if optim else {}

    def _full_model_state(self) -> dict[str, torch.Tensor]:
        from torch.distributed.checkpoint.state_dict import StateDictOptions, get_model_state_dict

        state = get_model_state_dict(self.net, options=StateDictOptions(full_state_dict=True, cpu_offload=True))
        return {name.removeprefix("policy."): t for name, t in state.items()}

    def _by_name(self, state: dict) -> dict:
        """``Optimizer.state_dict`` (params by index) -> keyed by parameter name, as torch.distributed wants."""
        return {"state": {self.names[i]: slots for i, slots in state["state"].items()},
                "param_groups": [{**g, "params": [self.names[i] for i in g["params"]]} for g in state["param_groups"]]}

    def _by_index(self, state: dict) -> dict:
        index = {name: i for i, name in enumerate(self.names)}
        return {"state": {index[name]: slots for name, slots in state["state"].items()},
                "param_groups": [{**g, "params": [index[n] for n in g["params"]]} for g in state["param_groups"]]}

    def all_sum(self, values: np.ndarray) -> np.ndarray:
        """Element-wise sum of ``values`` over the ranks (a collective), in float64."""
        total = torch.from_numpy(np.array(values, dtype=np.float64)).to(self.device)
        dist.all_reduce(total)
        return total.cpu().numpy()

    def send(self, command: Command | list[Command]) -> Command:
        """Rank 0: scatter one command per rank (or the same to all); return rank 0's own."""
        commands = command if isinstance(command, list) else [command] * self.world
        self._scatter([encode_command(c, self.wire) for c in commands])
        return commands[0]

    def receive(self) -> Command:
        """Ranks > 0: wait for rank 0's next command."""
        return decode_command(self._scatter(None), self.wire)

    def _scatter(self, payloads: list[bytes] | None) -> bytes:
        """Rank 0's ``payloads[r]`` to each rank r, a collective of byte tensors (scatter_object_list would
        unpickle what arrives): the longest length first, then each payload behind its own length."""
        device = self.device if self.backend == "nccl" else torch.device("cpu")
        size = torch.tensor([max(map(len, payloads)) if payloads else 0], dtype=torch.int64, device=device)
        dist.broadcast(size, src=0)
        n = int(size.item())
        mine = torch.empty(8 + n, dtype=torch.uint8, device=device)
        chunks = None if payloads is None else [
            torch.frombuffer(bytearray(struct.pack("<q", len(p)) + p + bytes(n - len(p))), dtype=torch.uint8).to(device)
            for p in payloads]
        dist.scatter(mine, chunks, src=0)
        raw = mine.cpu().numpy().tobytes()
        (length,) = struct.unpack("<q", raw[:8])
        if not 0 <= length <= n:
            raise MessageError(f"a rank command of {length} bytes in a buffer of {n}")
        return raw[8:8 + length]

    def close(self) -> None:
        """Leave the process group. DDP's reducer (and its logger) are let go first, while the group is still
        registered: a process group whose last holder is the reducer is destroyed inside the reducer's
        deallocation, which holds the GIL while it joins gloo's worker threads, and a worker thread that is
        freeing a finished work may need the GIL for it (a deadlock when the rank's objects go). Destroyed from
        the registry, the group is freed without the GIL.

        The ranks first meet at a barrier: a rank that destroyed its group while another still finished the last
        collective (FSDP's gathers for weights and checkpoints) aborted that one in gloo ("terminate called
        without an active exception", SIGABRT). A dead
        peer fails the barrier (or it times out after ``CLOSE_BARRIER_S``); the group goes anyway."""
        if isinstance(self.net, nn.parallel.DistributedDataParallel):
            for attr in ("logger", "reducer"):
                if getattr(self.net, attr, None) is not None:
                    setattr(self.net, attr, None)
        if dist.is_initialized():
            try:
                dist.barrier(async_op=True).wait(timeout=datetime.timedelta(seconds=CLOSE_BARRIER_S))
            except RuntimeError as exc:  # a peer gone or stuck: nothing is left to wait for
                log.warning("leaving the process group without the other ranks: %s", exc)
            dist.destroy_process_group()
