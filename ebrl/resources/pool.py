"""The GPU-CPU resource pool: what this host has, what each stage may use, and how a worker is bound to it.

* **Discovery.** CPU cores are the ones this process may use (``sched_getaffinity``,
  which already reflects a cgroup cpuset), capped by a cgroup CPU quota
  (``cpu.max``), each tagged with its NUMA node (``/sys/devices/system/node``).
  GPUs come from NVML: memory, MIG mode and MIG instance UUIDs; the SM count of a
  whole GPU from CUDA (torch), of a MIG instance from NVML.
* **Descriptors.** Per stage and GPU, an SM quota in percent and a memory budget
  (``set_quota``); the quotas of one GPU never add up to more than 100 %.
* **Bindings.** One :class:`WorkerResourceBinding` per worker: its cores, torch
  threads, GPU share and the environment variables its process must be
  launched with (``bind``); ``rebind`` moves a running worker to other cores.
* **Backends.** ``mps``: ``CUDA_MPS_ACTIVE_THREAD_PERCENTAGE`` and
  ``CUDA_MPS_PINNED_DEVICE_MEM_LIMIT`` injected at launch (fixed for the
  process's lifetime), after checking that an MPS control daemon is reachable;
  ``mig``: ``CUDA_VISIBLE_DEVICES`` = a pre-created MIG instance UUID; ``none``:
  whole devices. Without a GPU the pool partitions *cores* between simulation,
  generation and training (``partition``), which is what the allocator tunes on
  CPU-only machines.
"""

from __future__ import annotations

import dataclasses
import math
import os
import shutil
import subprocess
from pathlib import Path
from typing import Any, Literal

from ebrl.resources.nvml import load_nvml

MPS_PIPE_DEFAULT = "/tmp/nvidia-mps"


class ResourceError(ValueError):
    """A request the pool cannot satisfy; the message says what is missing."""


@dataclasses.dataclass(frozen=True)
class Core:
    id: int
    numa: int


@dataclasses.dataclass(frozen=True)
class MigInstance:
    uuid: str
    sm_count: int | None
    memory_bytes: int


@dataclasses.dataclass(frozen=True)
class Gpu:
    index: int
    uuid: str
    name: str
    memory_bytes: int
    sm_count: int | None
    mig_enabled: bool
    mig_instances: tuple[MigInstance, ...] = ()


@dataclasses.dataclass
class StageDescriptor:
    """What one stage may use of one GPU: the paper's (s, m)."""

    stage: str
    gpu: int
    sm_percent: float
    mem_bytes: int


@dataclasses.dataclass
class WorkerResourceBinding:
    """Everything one worker process is bound to; ``env`` goes into its environment at launch."""

    worker: str
    stage: str
    cores: list[int]
    threads: int
    gpu: int | None = None
    sm_percent: float | None = None
    mem_bytes: int | None = None
    mig_uuid: str | None = None
    env: dict[str, str] = dataclasses.field(default_factory=dict)


def mps_env(gpu: int, sm_percent: float, mem_bytes: int) -> dict[str, str]:
    """The environment an MPS client process starts with to get ``sm_percent`` of ``gpu``'s SMs and at most
    ``mem_bytes`` of its memory. MPS reads it when the process creates its CUDA context: a new share needs a
    new process."""
    return {"CUDA_VISIBLE_DEVICES": str(gpu), "CUDA_MPS_ACTIVE_THREAD_PERCENTAGE": f"{sm_percent:g}",
            # device 0 of the client: CUDA_VISIBLE_DEVICES leaves it one device
            "CUDA_MPS_PINNED_DEVICE_MEM_LIMIT": f"0={max(1, mem_bytes // 2**20)}M"}


# --- discovery ------------------------------------------------------------------------


def parse_cpulist(text: str) -> list[int]:
    """``"0-3,8,10-11"`` -> ``[0, 1, 2, 3, 8, 10, 11]`` (the kernel's cpulist format)."""
    out: list[int] = []
    for part in text.strip().split(","):
        if not part:
            continue
        lo, _, hi = part.partition("-")
        out.extend(range(int(lo), int(hi or lo) + 1))
    return out


def numa_nodes(sys_root: str = "/sys") -> dict[int, int]:
    """core id -> NUMA node; empty where the kernel exposes no NUMA topology."""
    nodes: dict[int, int] = {}
    base = Path(sys_root) / "devices/system/node"
    for node_dir in sorted(base.glob("node[0-9]*")):
        try:
            cores = parse_cpulist((node_dir / "cpulist").read_text())
        except OSError:
            continue
        for core in cores:
            nodes[core] = int(node_dir.name[4:])
    return nodes


def cgroup_cpu_limit(cgroup_root: str = "/sys/fs/cgroup") -> float | None:
    """CPUs' worth of time the cgroup allows (``cpu.max`` v2, ``cpu.cfs_*`` v1), None without a limit."""
    root = Path(cgroup_root)
    try:
        quota, period = (root / "cpu.max").read_text().split()[:2]
        return None if quota == "max" else int(quota) / int(period)
    except (OSError, ValueError):
        pass
    try:
        quota_us = int((root / "cpu/cpu.cfs_quota_us").read_text())
        period_us = int((root / "cpu/cpu.cfs_period_us").read_text())
        return quota_us / period_us if quota_us > 0 else None
    except (OSError, ValueError):
        return None


def discover_cores(allowed: list[int] | None = None, numa: dict[int, int] | None = None,
                   cpu_limit: float | None = -1.0) -> list[Core]:
    """The cores this process may use, capped by the cgroup CPU quota, with their NUMA node."""
    allowed = sorted(os.sched_getaffinity(0)) if allowed is None else sorted(allowed)
    numa = numa_nodes() if numa is None else numa
    limit = cgroup_cpu_limit() if cpu_limit == -1.0 else cpu_limit
    if limit is not None:
        allowed = allowed[:max(1, math.ceil(limit))]  # a quota of 2.5 CPUs can keep 3 cores busy part-time
    return [Core(c, numa.get(c, 0)) for c in allowed]


def discover_gpus(nvml: Any | None, num_gpus: int | None = None) -> list[Gpu]:
    """GPUs through NVML (nothing without it); MIG instances where MIG is on."""
    if nvml is None:
        return []
    gpus = []
    count = nvml.nvmlDeviceGetCount()
    for i in range(count if num_gpus is None else min(count, num_gpus)):
        handle = nvml.nvmlDeviceGetHandleByIndex(i)
        mig = _mig_mode(nvml, handle)
        gpus.append(Gpu(index=i, uuid=_text(nvml.nvmlDeviceGetUUID(handle)), name=_text(nvml.nvmlDeviceGetName(handle)),
                        memory_bytes=int(nvml.nvmlDeviceGetMemoryInfo(handle).total), sm_count=_cuda_sm_count(i),
                        mig_enabled=mig, mig_instances=_mig_instances(nvml, handle) if mig else ()))
    return gpus


def _text(value: Any) -> str:
    return value.decode() if isinstance(value, bytes) else str(value)


def _mig_mode(nvml: Any, handle: Any) -> bool:
    try:
        current, _pending = nvml.nvmlDeviceGetMigMode(handle)
        return bool(current)
    except nvml.NVMLError:  # NOT_SUPPORTED on GPUs without MIG
        return False


def _mig_instances(nvml: Any, handle: Any) -> tuple[MigInstance, ...]:
    out = []
    for k in range(nvml.nvmlDeviceGetMaxMigDeviceCount(handle)):
        try:
            mig = nvml.nvmlDeviceGetMigDeviceHandleByIndex(handle, k)
        except nvml.NVMLError:  # NOT_FOUND: an empty slot
            continue
        try:
            sms = int(nvml.nvmlDeviceGetAttributes(mig).multiprocessorCount)
        except nvml.NVMLError:
            sms = None
        out.append(MigInstance(uuid=_text(nvml.nvmlDeviceGetUUID(mig)), sm_count=sms,
                               memory_bytes=int(nvml.nvmlDeviceGetMemoryInfo(mig).total)))
    return tuple(out)


def _cuda_sm_count(index: int) -> int | None:
    try:
        import torch

        if torch.cuda.is_available() and index < torch.cuda.device_count():
            return int(torch.cuda.get_device_properties(index).multi_processor_count)
    except Exception:
        pass
    return None


MPS_CONTROL = "nvidia-cuda-mps-control"
MPS_ASK_S = 5.0


def mps_reachable(pipe_dir: str | None = None) -> bool:
    """Whether an MPS control daemon listens in the pipe directory: its ``control`` pipe exists and the daemon
    answers there. The pipe outlives a daemon that has quit (seen on an H100: the daemon exited, its pipe
    stayed), so existence alone is not enough; where the control program is not on PATH it cannot be asked
    and the pipe's existence is the answer."""
    pipe_dir = pipe_dir or os.environ.get("CUDA_MPS_PIPE_DIRECTORY", MPS_PIPE_DEFAULT)
    if not os.path.exists(os.path.join(pipe_dir, "control")):
        return False
    control = shutil.which(MPS_CONTROL)
    if control is None:
        return True
    try:
        asked = subprocess.run([control], input="get_server_list\n", capture_output=True, text=True,
                               timeout=MPS_ASK_S, env=dict(os.environ, CUDA_MPS_PIPE_DIRECTORY=pipe_dir))
    except (OSError, subprocess.TimeoutExpired):
        return False
    return asked.returncode == 0 and "cannot find" not in (asked.stdout + asked.stderr).lower()


# --- the pool ------------------------------------------------------------------------------


class ResourcePool:
    """CPU cores and GPUs of this host, each stage's share of them and each worker's binding.

    The cores are those this process may use (affinity, cgroup quota), tagged with their NUMA node; the GPUs come
    from NVML. ``partition`` splits the cores between stages, ``set_quota`` gives a stage an SM share and memory
    budget of a GPU, ``bind`` makes a worker's binding (its cores, threads and the environment its process is
    launched with: MPS shares, a MIG instance) and ``rebind`` moves it. ``gpu_pool``: how a GPU is shared (``mps``,
    ``mig``, ``none``: whole devices); without a GPU the pool partitions cores alone."""

    def __init__(self, num_gpus: int | None = None, gpu_pool: Literal["mps", "mig", "none"] = "none",
                 cpu_pool: Literal["numa", "flat"] = "flat", *, nvml: Any | None = None, cores: list[Core] | None = None,
                 mps_pipe_dir: str | None = None):
        if gpu_pool not in ("mps", "mig", "none"):
            raise ResourceError(f"gpu_pool = {gpu_pool!r}: expected mps, mig or none")
        if cpu_pool not in ("numa", "flat"):
            raise ResourceError(f"cpu_pool = {cpu_pool!r}: expected numa or flat")
        self.gpu_pool, self.cpu_pool = gpu_pool, cpu_pool
        self.cores = cores if cores is not None else discover_cores()
        if not self.cores:
            raise ResourceError("no usable CPU core")
        self.gpus = discover_gpus(nvml if nvml is not None else (load_nvml() if num_gpus != 0 else None), num_gpus)
        if num_gpus is not None and len(self.gpus) < num_gpus:
            raise ResourceError(f"num_gpus = {num_gpus}, but this host has {len(self.gpus)} usable GPU(s)")
        if gpu_pool == "mps" and self.gpus and not mps_reachable(mps_pipe_dir):
            pipe = mps_pipe_dir or os.environ.get("CUDA_MPS_PIPE_DIRECTORY", MPS_PIPE_DEFAULT)
            raise ResourceError(f"gpu_pool = 'mps' but no MPS control daemon is reachable (no {pipe}/control): start "
                                "one with `nvidia-cuda-mps-control -d`, or use gpu_pool = 'mig' or 'none'")
        if gpu_pool == "mig":
            for gpu in self.gpus:
                if not gpu.mig_enabled or not gpu.mig_instances:
                    raise ResourceError(f"gpu_pool = 'mig' but GPU {gpu.index} ({gpu.name}) has no MIG instances: "
                                        "create them once with nvidia-smi mig, or use gpu_pool = 'mps' or 'none'")
        self.descriptors: dict[tuple[str, int], StageDescriptor] = {}
        self.bindings: dict[str, WorkerResourceBinding] = {}

    # --- facts ---------------------------------------------------------------------------

    @property
    def core_ids(self) -> list[int]:
        return [c.id for c in self.cores]

    def numa_groups(self) -> dict[int, list[int]]:
        groups: dict[int, list[int]] = {}
        for core in self.cores:
            groups.setdefault(core.numa if self.cpu_pool == "numa" else 0, []).append(core.id)
        return groups

    def describe(self) -> str:
        gpus = ", ".join(f"GPU{g.index} {g.name} {g.memory_bytes / 2**30:.0f} GiB"
                         + (f" MIG x{len(g.mig_instances)}" if g.mig_enabled else "") for g in self.gpus) or "no GPU"
        nodes = {c.numa for c in self.cores}
        return (f"{len(self.cores)} cores ({len(nodes)} NUMA node{'s' if len(nodes) > 1 else ''}), {gpus}, "
                f"gpu_pool={self.gpu_pool}")

    # --- CPU: partition the cores between stages -----------------------------------------

    def partition(self, counts: dict[str, int]) -> dict[str, list[int]]:
        """Disjoint core sets of the given sizes, stage by stage in the order given; with ``cpu_pool =
        "numa"`` a stage stays on one NUMA node when one has room. Raises if the cores do not suffice."""
        need = sum(counts.values())
        if need > len(self.cores):
            raise ResourceError(f"{need} cores requested ({counts}) but the pool has {len(self.cores)}")
        free = {node: list(ids) for node, ids in self.numa_groups().items()}
        out: dict[str, list[int]] = {}
        for stage, n in counts.items():
            node = next((k for k, ids in sorted(free.items(), key=lambda kv: len(kv[1])) if len(ids) >= n), None)
            if node is not None:  # best fit: the smallest node with room keeps larger ones whole
                out[stage], free[node] = free[node][:n], free[node][n:]
            else:  # spans nodes
                taken: list[int] = []
                for ids in free.values():
                    while ids and len(taken) < n:
                        taken.append(ids.pop(0))
                out[stage] = taken
        return out

    # --- GPU descriptors -----------------------------------------------------------------

    def set_quota(self, stage: str, gpu: int, sm_percent: float, mem_bytes: int | None = None) -> StageDescriptor:
        """Record ``stage``'s SM share and memory budget on ``gpu`` (applied when its workers launch);
        without ``mem_bytes`` the stage gets the memory other stages have not reserved."""
        if not 0 <= gpu < len(self.gpus):
            raise ResourceError(f"GPU {gpu} does not exist (the pool has {len(self.gpus)})")
        if not 0 < sm_percent <= 100:
            raise ResourceError(f"{stage}: sm_percent = {sm_percent} must be in (0, 100]")
        device = self.gpus[gpu]
        others = [d for (s, g), d in self.descriptors.items() if g == gpu and s != stage]
        mem = device.memory_bytes - sum(d.mem_bytes for d in others) if mem_bytes is None else int(mem_bytes)
        if sum(d.sm_percent for d in others) + sm_percent > 100 + 1e-9:
            raise ResourceError(f"GPU {gpu}: SM quotas would add up to {sum(d.sm_percent for d in others) + sm_percent:g} %"
                                f" ({', '.join(f'{d.stage} {d.sm_percent:g}' for d in others)}, {stage} {sm_percent:g})")
        if sum(d.mem_bytes for d in others) + mem > device.memory_bytes:
            raise ResourceError(f"GPU {gpu}: memory budgets exceed its {device.memory_bytes / 2**30:.1f} GiB")
        desc = StageDescriptor(stage, gpu, float(sm_percent), mem)
        self.descriptors[(stage, gpu)] = desc
        return desc

    def clear_quotas(self, gpu: int) -> None:
        """Forget every stage's share of ``gpu`` (before a new plan sets them all again)."""
        self.descriptors = {key: d for key, d in self.descriptors.items() if key[1] != gpu}

    # --- bindings ---------------------------------------------------------------------------

    def bind(self, worker: str, stage: str, cores: list[int], threads: int | None = None,
             gpu: int | None = None) -> WorkerResourceBinding:
        """Bind ``worker`` to ``cores`` (and ``stage``'s share of ``gpu``); the binding's ``env`` is what
        the worker's process must be launched with."""
        unknown = sorted(set(cores) - set(self.core_ids))
        if unknown or not cores:
            raise ResourceError(f"{worker}: cores {unknown or cores} are not in the pool ({self.core_ids})")
        binding = WorkerResourceBinding(worker, stage, sorted(cores), threads or len(cores))
        if gpu is not None:
            self._bind_gpu(binding, gpu)
        binding.env["OMP_NUM_THREADS"] = str(binding.threads)
        self.bindings[worker] = binding
        return binding

    def rebind(self, worker: str, cores: list[int], pid: int | None = None) -> WorkerResourceBinding:
        """Move a bound worker to other cores; with ``pid``, pin that running process now."""
        binding = self.bindings.get(worker)
        if binding is None:
            raise ResourceError(f"{worker} is not bound")
        unknown = sorted(set(cores) - set(self.core_ids))
        if unknown or not cores:
            raise ResourceError(f"{worker}: cores {unknown or cores} are not in the pool ({self.core_ids})")
        binding.cores = sorted(cores)
        if pid is not None:
            os.sched_setaffinity(pid, binding.cores)
        return binding

    def _bind_gpu(self, binding: WorkerResourceBinding, gpu: int) -> None:
        if not 0 <= gpu < len(self.gpus):
            raise ResourceError(f"{binding.worker}: GPU {gpu} does not exist (the pool has {len(self.gpus)})")
        binding.gpu = gpu
        device = self.gpus[gpu]
        if self.gpu_pool == "mig":
            used = {b.mig_uuid for b in self.bindings.values() if b.worker != binding.worker}
            free = [m for m in device.mig_instances if m.uuid not in used]
            if not free:
                raise ResourceError(f"{binding.worker}: every MIG instance of GPU {gpu} is taken")
            binding.mig_uuid = free[0].uuid
            binding.env["CUDA_VISIBLE_DEVICES"] = free[0].uuid
            return
        binding.env["CUDA_VISIBLE_DEVICES"] = str(gpu)
        if self.gpu_pool == "mps":
            desc = self.descriptors.get((binding.stage, gpu))
            if desc is None:
                raise ResourceError(f"{binding.worker}: no quota for stage {binding.stage} on GPU {gpu} (set_quota first)")
            binding.sm_percent, binding.mem_bytes = desc.sm_percent, desc.mem_bytes
            binding.env.update(mps_env(gpu, desc.sm_percent, desc.mem_bytes))
