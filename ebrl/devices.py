"""Where generation and training run: ``gen.device`` and ``train.device``, their memory cap, their stats.

``"auto"`` (the default) is the GPU the process is bound to when torch sees one (the launcher binds a
stage with ``CUDA_VISIBLE_DEVICES``, so that is ``cuda:0`` inside it), else the CPU; ``"cpu"``, ``"cuda"``
and ``"cuda:N"`` ask for one. A device that does not exist is a config error naming the field, found by
``ebrl up`` before anything starts (``preflight``).

A stage's GPU memory budget (the allocator's ``Quota.mem_bytes``, or ``CUDA_MPS_PINNED_DEVICE_MEM_LIMIT``
set at launch) becomes the process's CUDA caching-allocator cap
(``torch.cuda.set_per_process_memory_fraction``): an allocation past it fails in that process, as the
MPS limit makes it fail at the driver.
"""

from __future__ import annotations

import os
import re
from typing import Any

import numpy as np

_SYNTAX = re.compile(r"^(auto|cpu|cuda|cuda:\d+)$")
MPS_MEM_VAR = "CUDA_MPS_PINNED_DEVICE_MEM_LIMIT"  # "0=1024M": device 0, at most 1024 MiB (MPS's format)
_UNITS = {"": 1, "K": 1 << 10, "M": 1 << 20, "G": 1 << 30, "T": 1 << 40}


class DeviceError(ValueError):
    """A device setting that cannot be honoured here; the message names the field."""


def check_syntax(value: str, field: str) -> None:
    """Raise DeviceError unless ``value`` is auto, cpu, cuda or cuda:N (no torch import: config time)."""
    if not _SYNTAX.match(value):
        raise DeviceError(f"{field} = {value!r}: expected \"auto\", \"cpu\", \"cuda\" or \"cuda:N\"")


def cuda_available() -> bool:
    """Whether torch sees a CUDA GPU here (imports torch)."""
    import torch

    return torch.cuda.is_available()


def is_cuda(value: str) -> bool:
    """Whether ``value`` (auto, cpu, cuda, cuda:N) means a CUDA device here; ``auto``: where torch sees one."""
    if value == "auto":
        return cuda_available()
    return value.startswith("cuda")


def physx_backend(value: str | None) -> str:
    """The PhysX backend a ManiSkill ``sim_backend`` names here. Absent: ``physx_cpu`` (one env per worker
    process, pinned to a core). ``"auto"``: ``physx_cuda`` where torch sees a CUDA GPU (each group then one
    vectorized batch on it, ``sim.vectorized``), else ``physx_cpu``."""
    if value == "auto":
        return "physx_cuda" if cuda_available() else "physx_cpu"
    return value or "physx_cpu"


def resolve(value: str, field: str) -> Any:
    """The ``torch.device`` that ``value`` names on this machine; DeviceError if it does not exist."""
    import torch

    check_syntax(value, field)
    available = torch.cuda.is_available()
    if value == "auto":
        return torch.device("cuda", torch.cuda.current_device()) if available else torch.device("cpu")
    if value == "cpu":
        return torch.device("cpu")
    if not available:
        raise DeviceError(f"{field} = {value!r}: torch sees no CUDA device here (torch {torch.__version__}, "
                          f"CUDA build: {torch.version.cuda or 'no'}); use \"cpu\" or \"auto\"")
    index = int(value.split(":")[1]) if ":" in value else torch.cuda.current_device()
    if index >= torch.cuda.device_count():
        raise DeviceError(f"{field} = {value!r}: this process sees {torch.cuda.device_count()} CUDA device(s) "
                          f"(CUDA_VISIBLE_DEVICES={os.environ.get('CUDA_VISIBLE_DEVICES', 'unset')})")
    return torch.device("cuda", index)


def preflight(cfg: Any, roles: tuple[str, ...] = ("gen", "train")) -> str | None:
    """The first device setting of ``cfg`` (of the stages in ``roles``: those this host runs) that cannot run
    here, as an error naming its field (None: fine). ``auto`` and ``cpu`` always can: torch is not even loaded."""
    for role in ("gen", "train"):
        field, value = f"{role}.device", getattr(cfg, role).device
        if role not in roles or value in ("auto", "cpu"):
            continue
        try:
            resolve(value, field)
        except DeviceError as exc:
            return str(exc)
    return None


def rank_device(value: str, field: str, rank: int) -> Any:
    """Data-parallel rank ``rank``'s device: ``cuda`` and ``auto`` spread the ranks over the visible GPUs
    (one each where there are enough, else they share); ``cuda:N`` and ``cpu`` are taken as they are."""
    import torch

    device = resolve(value, field)
    if device.type == "cuda" and value in ("auto", "cuda"):
        device = torch.device("cuda", rank % torch.cuda.device_count())
    return device


def parse_mps_limit(text: str, index: int = 0) -> int | None:
    """Bytes that ``CUDA_MPS_PINNED_DEVICE_MEM_LIMIT`` (``"0=1024M,1=2G"``) allows on device ``index``."""
    for item in filter(None, (part.strip() for part in text.split(","))):
        device, _, size = item.partition("=")
        match = re.fullmatch(r"(\d+)([KMGT]?)B?", size.strip().upper())
        if device.strip() == str(index) and match:
            return int(match.group(1)) * _UNITS[match.group(2)]
    return None


def apply_memory_cap(device: Any, mem_bytes: int | None) -> float | None:
    """Cap this process's CUDA allocations on ``device`` at ``mem_bytes``; the fraction set (None: no cap,
    on the CPU or without a budget)."""
    import torch

    if device.type != "cuda" or not mem_bytes:
        return None
    total = torch.cuda.get_device_properties(device).total_memory
    fraction = min(1.0, mem_bytes / total)
    torch.cuda.set_per_process_memory_fraction(fraction, device)
    return fraction


def launch_memory_cap(device: Any) -> float | None:
    """The cap the launcher's GPU share asks for (its MPS memory limit), applied at start."""
    limit = os.environ.get(MPS_MEM_VAR)
    return apply_memory_cap(device, parse_mps_limit(limit, 0)) if limit else None


def autocast(device: Any, dtype: str) -> Any:
    """The context ``policy.dtype`` asks for on ``device``: bfloat16 autocast, or nothing for float32."""
    import contextlib

    import torch

    if dtype == "bfloat16":
        return torch.autocast(device.type, dtype=torch.bfloat16)
    return contextlib.nullcontext()


def cpu_has_bf16() -> bool:
    """Whether this CPU multiplies bfloat16 matrices in hardware (AVX-512 BF16 or AMX's tiles; /proc/cpuinfo's
    flags): where it does not, bfloat16 autocast on the CPU is emulated, slower than float32."""
    try:
        with open("/proc/cpuinfo") as fh:
            flags = next((line.split(":", 1)[1].split() for line in fh if line.startswith("flags")), [])
    except OSError:
        return False
    return bool({"avx512_bf16", "amx_bf16"} & set(flags))


def dtype_bits(dtype: str) -> float:
    """``policy.dtype`` as the bits of its matrix products, for the stats (``gen/dtype``, ``train/dtype``): 16
    for bfloat16 autocast, 32 otherwise."""
    return 16.0 if dtype == "bfloat16" else 32.0


def describe(device: Any) -> str:
    """``cpu``, or ``cuda:0 (NVIDIA H100 80GB HBM3, 79.1 GiB)``: for the log and the run's events."""
    import torch

    if device.type != "cuda":
        return str(device)
    props = torch.cuda.get_device_properties(device)
    return f"{device} ({props.name}, {props.total_memory / 2**30:.1f} GiB)"


def metrics(prefix: str, device: Any, cap: float | None) -> dict[str, float]:
    """``<prefix>/cuda_device`` (-1 on the CPU), memory in use and reserved, and the cap, in MiB."""
    import torch

    if device.type != "cuda":
        return {f"{prefix}/cuda_device": -1.0}
    total = torch.cuda.get_device_properties(device).total_memory
    return {f"{prefix}/cuda_device": float(device.index),
            f"{prefix}/cuda_mem_allocated_mb": torch.cuda.memory_allocated(device) / 2**20,
            f"{prefix}/cuda_mem_reserved_mb": torch.cuda.memory_reserved(device) / 2**20,
            f"{prefix}/cuda_mem_cap_mb": (cap if cap is not None else 1.0) * total / 2**20}


class Staging:
    """Host arrays to ``device`` through one reused pinned buffer, copied without blocking the host thread; on
    the CPU, a view of the array. The caller reads the results back (``ebrl.policies.base.to_host``) before it
    stages the next batch, so the buffer is never overwritten while a copy from it is in flight."""

    def __init__(self, device: Any):
        self.device = device
        self.buffer: Any = None

    def __call__(self, array: np.ndarray) -> Any:
        import torch

        host = torch.from_numpy(np.ascontiguousarray(array, dtype=np.float32))
        if self.device.type != "cuda":
            return host
        if self.buffer is None or self.buffer.numel() < host.numel():
            self.buffer = torch.empty(host.numel(), dtype=torch.float32).pin_memory()
        staged = self.buffer[:host.numel()].view(host.shape)
        staged.copy_(host)
        return staged.to(self.device, non_blocking=True)

