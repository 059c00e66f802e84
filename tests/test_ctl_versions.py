"""Control versions and requotas (issue 52): a control version far past the last applied is refused and counted,
so a forged 2**53 no longer pins a service; a flood of GPU shares cannot restart a stage forever."""

from __future__ import annotations

import asyncio
import io
import os
import signal
import sys
import time
import types

from ebrl import config
from ebrl import keys
from ebrl.bus.memory import MemoryBus, MemoryNetwork
from ebrl.messages import Affinity, GpuShare, Quota
from ebrl.service import CONTROL_STEP, Service, control_version_refused
from ebrl.supervisor import RestartPolicy, Supervisor
from helpers import ROOT, until

WAIT_S = 60.0  # a bound for a hang, not a timing window


class Controlled(Service):
    role = "gen"

    def __init__(self, cfg):
        super().__init__(cfg, 0)
        self.applied: list[tuple[str, int]] = []

    def on_affinity(self, cores: list[int]) -> None:
        self.applied.append(("affinity", cores[0]))

    def on_quota(self, quota: Quota) -> None:
        self.applied.append(("quota", quota.threads))


def test_a_control_version_far_past_the_last_applied_is_refused_counted_and_pins_nothing():
    assert control_version_refused(CONTROL_STEP, 0) is None and control_version_refused(CONTROL_STEP + 1, 0)
    assert control_version_refused(2**53, 5) and control_version_refused(5 + CONTROL_STEP, 5) is None
    cfg = config.from_dict({"run": {"name": "ctl", "stats_interval": 0.2}})

    async def scenario():
        network = MemoryNetwork()
        bus, service_bus = MemoryBus(network), MemoryBus(network)
        service = Controlled(cfg)
        task = asyncio.create_task(service.main(bus=service_bus, signals=False))
        await until(lambda: getattr(service, "controls", None) is not None, WAIT_S, "the service's control keys")
        sent = [("quota", Quota(version=2**53, threads=7)), ("affinity", Affinity(version=2**53, cores=[7])),
                ("quota", Quota(version=CONTROL_STEP + 1, threads=6)),  # more than a step past 0
                ("quota", Quota(version=1, threads=1)), ("affinity", Affinity(version=2, cores=[2])),
                ("quota", Quota(version=1 + CONTROL_STEP, threads=3)),  # a step past the last applied, 1
                ("quota", Quota(version=2 + 2 * CONTROL_STEP, threads=4))]  # one more than a step past 1001
        for kind, msg in sent:
            await bus.put(keys.ctl("ctl", "gen", 0, kind), msg)
            await until(lambda: service.meter.total("ctl/version_refused") + len(service.applied) >= sent.index(
                (kind, msg)) + 1, WAIT_S, f"{kind} v{msg.version} taken or refused")  # in order: one at a time
        assert service.applied == [("quota", 1), ("affinity", 2), ("quota", 3)]
        assert service.meter.total("ctl/version_refused") == 4
        assert service._report().metrics["ctl/version_refused"] == 4  # where a user sees it
        service.request_stop("test")
        assert await asyncio.wait_for(task, WAIT_S) == 0
        await bus.close()

    asyncio.run(scenario())


SLEEPER = "import time; print('up', flush=True); time.sleep(600)"


def test_requotas_count_against_max_restarts_and_then_the_run_ends_with_a_clear_failure(tmp_path):
    said: list[str] = []
    events: list[tuple[str, str]] = []
    share = "CUDA_MPS_ACTIVE_THREAD_PERCENTAGE"
    sup = Supervisor(lambda role, instance: [sys.executable, "-c", SLEEPER], tmp_path,
                     RestartPolicy(True, 2, first_delay_s=0.01), say=said.append,
                     event=lambda kind, text: events.append((kind, text)), gpu_env={"gen": {share: "50"}})
    child = sup.start("gen", 0)
    try:
        for version, percent in ((2, "40"), (3, "30")):  # two requotas: as many as run.max_restarts = 2
            assert sup.new_gpu_share("gen", {share: percent}, version) == [child]
            child.proc.terminate()  # it stops at its safe point (asked over the bus)
            deadline = time.monotonic() + WAIT_S
            while child.requota or child.proc.poll() is not None:
                assert sup.check() is None and time.monotonic() < deadline, "gen not started again"
                time.sleep(0.02)
        assert child.requotas == 2 and child.restarts == 0 and sup.check() is None
        assert sup.new_gpu_share("gen", {share: "20"}, 4) == []  # a third: refused, not started again
        failure = sup.check()
        assert failure and "gen/0" in failure and "run.max_restarts = 2" in failure and "version 4" in failure
        assert child.proc.poll() is None  # nothing was stopped for it
        assert any(failure in line for line in said) and ("exited", failure) in events
        assert sup.metrics()["launcher/requotas"] == 2.0
    finally:
        os.killpg(child.proc.pid, signal.SIGKILL)
        child.proc.wait(5)


def test_the_launcher_refuses_a_gpu_share_far_past_the_stages_last_and_counts_it(tmp_path):
    from ebrl.launch import Launcher

    cfg = config.load(ROOT / "configs" / "quickstart.toml")
    share = {"CUDA_MPS_ACTIVE_THREAD_PERCENTAGE": "50"}
    launcher = Launcher(cfg, tmp_path, out=io.StringIO(), gpu_env={"gen": share})
    asked: list[tuple[str, int]] = []
    from ebrl.launch import LauncherBus

    launcher.link = types.SimpleNamespace(refused=__import__("collections").Counter())
    launcher.link.refuse = lambda counter, line, say: LauncherBus.refuse(launcher.link, counter, line, say)
    launcher.supervisor = types.SimpleNamespace(share_versions={"gen": 3},
                                                new_gpu_share=lambda s, env, v: asked.append((s, v)) or [])
    launcher.on_gpu_share("k", GpuShare(version=2**53, stage="gen", env=share))
    launcher.on_gpu_share("k", GpuShare(version=3 + CONTROL_STEP + 1, stage="gen", env=share))
    assert asked == [] and launcher.link.refused["ctl/version_refused"] == 2
    launcher.on_gpu_share("k", GpuShare(version=3 + CONTROL_STEP, stage="gen", env=share))
    assert asked == [("gen", 3 + CONTROL_STEP)] and launcher.link.refused["launcher/gpu_shares_refused"] == 0
