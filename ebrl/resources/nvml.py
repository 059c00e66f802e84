"""GPU discovery and utilisation through NVML, tolerant of machines without a GPU.

NVML comes from ``nvidia-ml-py`` (the ``pynvml`` module). Without the NVIDIA
driver library, or without GPUs, every call here returns nothing instead of
failing: a CPU-only host simply reports no ``gpu/*`` metrics. Calls a device
does not support (NOT_SUPPORTED, e.g. utilisation of a MIG instance) are
skipped per metric.
"""

from __future__ import annotations

import logging
from typing import Any

log = logging.getLogger("ebrl.resources")


def load_nvml() -> Any | None:
    """The initialised ``pynvml`` module, or None where NVML is not available."""
    try:
        import pynvml
    except ImportError:
        return None
    try:
        pynvml.nvmlInit()
    except pynvml.NVMLError as exc:  # no driver library, no device, insufficient permissions
        log.debug("NVML unavailable: %s", exc)
        return None
    return pynvml


class GpuMonitor:
    """Samples SM and memory utilisation of every GPU of this host (``gpu/<i>_*`` metrics)."""

    def __init__(self, nvml: Any | None = None):
        self.nvml = nvml if nvml is not None else load_nvml()
        self.handles: list[Any] = []
        if self.nvml is not None:
            try:
                self.handles = [self.nvml.nvmlDeviceGetHandleByIndex(i)
                                for i in range(self.nvml.nvmlDeviceGetCount())]
            except self.nvml.NVMLError as exc:
                log.warning("NVML: cannot list GPUs: %s", exc)

    def sample(self) -> dict[str, float]:
        out: dict[str, float] = {}
        for i, handle in enumerate(self.handles):
            try:
                util = self.nvml.nvmlDeviceGetUtilizationRates(handle)
                out[f"gpu/{i}_sm_percent"] = float(util.gpu)
            except self.nvml.NVMLError:
                pass
            try:
                mem = self.nvml.nvmlDeviceGetMemoryInfo(handle)
                out[f"gpu/{i}_mem_used_mb"] = mem.used / 2**20
                out[f"gpu/{i}_mem_total_mb"] = mem.total / 2**20
            except self.nvml.NVMLError:
                pass
        return out
