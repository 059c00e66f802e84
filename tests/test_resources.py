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


# --- the resource pool -------------------------------------------------------------------------

import os  # noqa: E402

import pytest  # noqa: E402

from ebrl.resources.pool import (Core, ResourceError, ResourcePool, cgroup_cpu_limit, discover_cores,  # noqa: E402
                                 numa_nodes, parse_cpulist)


class FakeGpuNVML(FakeNVML):
    """Two GPUs: GPU 0 plain (80 GiB), GPU 1 with MIG on and two instances in slots 0 and 2
    (``only_mig=True``: just the MIG GPU, as device 0)."""

    def __init__(self, only_mig=False):
        self.devices = ["h1"] if only_mig else ["h0", "h1"]

    def nvmlDeviceGetCount(self):
        return len(self.devices)

    def nvmlDeviceGetHandleByIndex(self, i):
        return self.devices[i]

    def nvmlDeviceGetUUID(self, handle):
        return {"h0": "GPU-aaaa", "h1": "GPU-bbbb", "m0": "MIG-1111", "m2": "MIG-2222"}[handle]

    def nvmlDeviceGetName(self, handle):
        return b"NVIDIA H200"

    def nvmlDeviceGetMigMode(self, handle):
        if handle == "h0":
            raise self.NVMLError("NOT_SUPPORTED")
        return (1, 1)

    def nvmlDeviceGetMaxMigDeviceCount(self, handle):
        return 3

    def nvmlDeviceGetMigDeviceHandleByIndex(self, handle, k):
        if k == 1:
            raise self.NVMLError("NOT_FOUND")
        return f"m{k}"

    def nvmlDeviceGetAttributes(self, handle):
        return types.SimpleNamespace(multiprocessorCount={"m0": 16, "m2": 32}[handle])

    def nvmlDeviceGetMemoryInfo(self, handle):
        total = {"h0": 80, "h1": 80, "m0": 10, "m2": 20}[handle] * 2**30
        return types.SimpleNamespace(used=0, total=total, free=total)


CORES = [Core(i, 0 if i < 4 else 1) for i in range(8)]


def test_cpulist_numa_and_cgroup_parsing(tmp_path):
    assert parse_cpulist("0-3,8,10-11\n") == [0, 1, 2, 3, 8, 10, 11]
    for node, cpus in ((0, "0-1"), (1, "2-3")):
        (tmp_path / f"devices/system/node/node{node}").mkdir(parents=True)
        (tmp_path / f"devices/system/node/node{node}/cpulist").write_text(cpus)
    assert numa_nodes(str(tmp_path)) == {0: 0, 1: 0, 2: 1, 3: 1}
    (tmp_path / "cg").mkdir()
    (tmp_path / "cg/cpu.max").write_text("250000 100000\n")
    assert cgroup_cpu_limit(str(tmp_path / "cg")) == 2.5
    (tmp_path / "cg/cpu.max").write_text("max 100000\n")
    assert cgroup_cpu_limit(str(tmp_path / "cg")) is None
    cores = discover_cores(allowed=[0, 1, 2, 3], numa={0: 0, 1: 0, 2: 1, 3: 1}, cpu_limit=2.5)
    assert cores == [Core(0, 0), Core(1, 0), Core(2, 1)]  # 2.5 CPUs of quota: three cores, part-time
    assert [c.id for c in discover_cores()] == sorted(os.sched_getaffinity(0))[:len(discover_cores())]


def test_partition_keeps_stages_on_one_numa_node_and_refuses_too_much():
    pool = ResourcePool(cpu_pool="numa", cores=CORES, nvml=None, num_gpus=0)
    parts = pool.partition({"sim": 4, "gen": 2, "train": 2})
    assert sorted(parts["sim"]) in ([0, 1, 2, 3], [4, 5, 6, 7])
    assert {c // 4 for c in parts["gen"]} == {c // 4 for c in parts["train"]}  # both on the other node
    assert sorted(parts["sim"] + parts["gen"] + parts["train"]) == list(range(8))
    with pytest.raises(ResourceError, match="9 cores requested"):
        pool.partition({"sim": 8, "gen": 1})


def test_bind_and_rebind_cpu_workers():
    pool = ResourcePool(cores=CORES, num_gpus=0)
    binding = pool.bind("sim/0", "sim", [0, 1])
    assert binding.threads == 2 and binding.env == {"OMP_NUM_THREADS": "2"} and binding.gpu is None
    with pytest.raises(ResourceError, match=r"cores \[9\] are not in the pool"):
        pool.bind("gen/0", "gen", [9])
    me = os.getpid()
    before = sorted(os.sched_getaffinity(0))
    try:
        assert pool.rebind("sim/0", [before[0]], pid=me).cores == [before[0]]
        assert sorted(os.sched_getaffinity(0)) == [before[0]]
    finally:
        os.sched_setaffinity(0, before)
    with pytest.raises(ResourceError, match="not bound"):
        pool.rebind("train/0", [0])


def test_gpu_discovery_through_nvml():
    pool = ResourcePool(nvml=FakeGpuNVML(), cores=CORES)
    g0, g1 = pool.gpus
    assert (g0.uuid, g0.name, g0.mig_enabled, g0.memory_bytes) == ("GPU-aaaa", "NVIDIA H200", False, 80 * 2**30)
    assert g1.mig_enabled and [(m.uuid, m.sm_count) for m in g1.mig_instances] == [("MIG-1111", 16), ("MIG-2222", 32)]
    assert "2 NUMA nodes" in pool.describe() and "MIG x2" in pool.describe()
    with pytest.raises(ResourceError, match="num_gpus = 3"):
        ResourcePool(num_gpus=3, nvml=FakeGpuNVML(), cores=CORES)


def test_mps_backend_injects_quotas_and_needs_a_daemon(tmp_path):
    with pytest.raises(ResourceError, match="no MPS control daemon is reachable"):
        ResourcePool(gpu_pool="mps", nvml=FakeGpuNVML(), cores=CORES, mps_pipe_dir=str(tmp_path))
    (tmp_path / "control").write_text("")  # the daemon's control pipe
    pool = ResourcePool(gpu_pool="mps", nvml=FakeGpuNVML(), cores=CORES, mps_pipe_dir=str(tmp_path))
    pool.set_quota("gen", 0, 30, mem_bytes=8 * 2**30)
    pool.set_quota("train", 0, 70)
    with pytest.raises(ResourceError, match="would add up to 110"):
        pool.set_quota("sim", 0, 10)
    with pytest.raises(ResourceError, match="no quota for stage sim"):
        pool.bind("sim/0", "sim", [0], gpu=0)
    gen = pool.bind("gen/0", "gen", [4], threads=2, gpu=0)
    assert gen.env == {"CUDA_VISIBLE_DEVICES": "0", "CUDA_MPS_ACTIVE_THREAD_PERCENTAGE": "30",
                       "CUDA_MPS_PINNED_DEVICE_MEM_LIMIT": "0=8192M", "OMP_NUM_THREADS": "2"}
    pool.set_quota("gen", 0, 20)  # a new quota replaces the stage's old one
    assert pool.descriptors[("gen", 0)].sm_percent == 20


def test_mig_backend_hands_out_instance_uuids():
    with pytest.raises(ResourceError, match="GPU 0 .* has no MIG instances"):
        ResourcePool(gpu_pool="mig", nvml=FakeGpuNVML(), cores=CORES)
    pool = ResourcePool(gpu_pool="mig", nvml=FakeGpuNVML(only_mig=True), cores=CORES)
    a = pool.bind("gen/0", "gen", [0], gpu=0)
    b = pool.bind("train/0", "train", [1], gpu=0)
    assert (a.env["CUDA_VISIBLE_DEVICES"], b.env["CUDA_VISIBLE_DEVICES"]) == ("MIG-1111", "MIG-2222")
    with pytest.raises(ResourceError, match="every MIG instance of GPU 0 is taken"):
        pool.bind("sim/0", "sim", [2], gpu=0)
