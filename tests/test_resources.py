"""Resources: NVML GPU monitoring, with NVML faked at its boundary (no GPU on the development machines)."""

from __future__ import annotations

import types

from ebrl.resources.nvml import GpuMonitor, load_nvml


class FakeNVML:
    """The pynvml calls GpuMonitor uses; GPU 1 is a MIG-like device without utilisation counters."""

    class NVMLError(Exception):
        pass

    def nvmlDeviceGetCount(self):
        return 2

    def nvmlDeviceGetHandleByIndex(self, i):
        return f"h{i}"

    def nvmlDeviceGetUtilizationRates(self, handle):
        if handle == "h1":
            raise self.NVMLError("NOT_SUPPORTED")
        return types.SimpleNamespace(gpu=73, memory=12)

    def nvmlDeviceGetMemoryInfo(self, handle):
        return types.SimpleNamespace(used=3 * 2**30, total=80 * 2**30, free=77 * 2**30)


def test_gpu_monitor_reports_each_gpu_and_skips_unsupported_counters():
    sample = GpuMonitor(FakeNVML()).sample()
    assert sample == {"gpu/0_sm_percent": 73.0, "gpu/0_mem_used_mb": 3072.0, "gpu/0_mem_total_mb": 81920.0,
                      "gpu/1_mem_used_mb": 3072.0, "gpu/1_mem_total_mb": 81920.0}


def test_without_a_gpu_there_is_nothing_to_report():
    if load_nvml() is not None:  # a GPU machine: the real NVML answers
        assert isinstance(GpuMonitor().sample(), dict)
        return
    assert GpuMonitor().sample() == {}
