"""Control messages (``ebrl/ctl/...``): stop, CPU affinity, quotas, and a stage's new GPU share."""

from __future__ import annotations

import re
from dataclasses import dataclass
from typing import Literal

from ebrl.messages.common import CONTROL_MAX_BYTES, MAX_TEXT, MessageError, doc, in_range


@dataclass
class Stop:
    """Ask a service to stop gracefully."""

    KEY = "ebrl/ctl/<run>/<service>/<instance>/stop"
    reason: str = doc("why, for the log")

    MAX_BYTES = CONTROL_MAX_BYTES

    def check(self) -> None:
        if len(self.reason) > MAX_TEXT:
            raise MessageError(f"Stop.reason: {len(self.reason)} characters, more than {MAX_TEXT}")


@dataclass
class Affinity:
    """Pin a service's process (and the workers it owns) to CPU cores."""

    KEY = "ebrl/ctl/<run>/<service>/<instance>/affinity"
    version: int = doc("monotonic; an update with a version already applied is ignored")
    cores: list[int] = doc("CPU core ids")

    MAX_BYTES = CONTROL_MAX_BYTES

    def check(self) -> None:
        in_range("Affinity.version", self.version)
        if not self.cores or len(set(self.cores)) != len(self.cores) or not all(0 <= c < 1 << 16 for c in self.cores):
            raise MessageError(f"Affinity.cores = {self.cores[:8]}: expected distinct core ids, at least one")


@dataclass
class Quota:
    """Resource quota of a service: thread count and GPU share."""

    KEY = "ebrl/ctl/<run>/<service>/<instance>/quota"
    version: int = doc("monotonic; an update with a version already applied is ignored")
    threads: int | None = doc("torch intra-op threads", default=None)
    sm_percent: float | None = doc("GPU SM share in percent", default=None)
    mem_bytes: int | None = doc("GPU memory budget in bytes", default=None)
    batch: int | None = doc("batch size the stage should use (gen: most envs per forward pass)", default=None)

    MAX_BYTES = CONTROL_MAX_BYTES

    def check(self) -> None:
        in_range("Quota.version", self.version)
        if self.threads is not None:
            in_range("Quota.threads", self.threads, 1, 4096)
        if self.sm_percent is not None and not 0 < self.sm_percent <= 100:
            raise MessageError(f"Quota.sm_percent = {self.sm_percent}: outside (0, 100]")
        if self.mem_bytes is not None:
            in_range("Quota.mem_bytes", self.mem_bytes, 0, 1 << 50)
        if self.batch is not None:
            in_range("Quota.batch", self.batch, 1, 1 << 24)


# The variables of a GPU share (ebrl.resources.pool.Binding.env), each with the values it may take: devices by
# index or UUID, an SM percentage, MPS's per-device memory limits ("0=1024M").
GPU_SHARE_VARIABLES = {
    "CUDA_VISIBLE_DEVICES": r"(\d{1,3}|(GPU|MIG)-[0-9A-Za-z/-]{1,80})(,(\d{1,3}|(GPU|MIG)-[0-9A-Za-z/-]{1,80})){0,15}",
    "CUDA_MPS_ACTIVE_THREAD_PERCENTAGE": r"(100|[1-9]?\d)(\.\d{1,6})?",
    "CUDA_MPS_PINNED_DEVICE_MEM_LIMIT": r"\d{1,3}=\d{1,9}[MG](,\d{1,3}=\d{1,9}[MG]){0,15}",
}


@dataclass
class GpuShare:
    """Start one stage's processes again with a new GPU share (allocator -> the launcher of its host). MPS
    fixes a process's share when it makes its CUDA context: the launcher stops the stage's processes at their
    safe point (``Stop``, reason ``STOP_TO_RESTART``) and starts them with ``env`` (counted in
    ``launcher/requotas``); only in a run with the allocator. ``env`` holds only the variables a share is made
    of (:data:`GPU_SHARE_VARIABLES`), each in its own format: anything else (a library for CUDA to load) is
    refused."""

    KEY = "ebrl/ctl/<run>/launcher/<host>/gpu_share"
    version: int = doc("plan version; a share whose version the stage already has is ignored")
    stage: Literal["gen", "train"] = doc("the stage whose processes take the share")
    env: dict[str, str] = doc("the CUDA variables its processes start with: CUDA_VISIBLE_DEVICES, CUDA_MPS_*")

    MAX_BYTES = CONTROL_MAX_BYTES

    def check(self) -> None:
        in_range("GpuShare.version", self.version)

    def __post_init__(self) -> None:
        other = sorted(k for k in self.env if k not in GPU_SHARE_VARIABLES)
        if other:
            raise MessageError(f"GpuShare: env may only set {', '.join(GPU_SHARE_VARIABLES)}, not {', '.join(other)}")
        for name, value in self.env.items():
            if not re.fullmatch(GPU_SHARE_VARIABLES[name], value):
                raise MessageError(f"GpuShare: {name}={value!r} is not a share's value")
