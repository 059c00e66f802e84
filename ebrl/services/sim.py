"""sim service: environment groups in worker processes; observations out, action chunks in, segments to train.

The group pipeline itself is ``ebrl.sched.group``; the env workers and their stepping, ``ebrl.sched.fleet``.
"""

from __future__ import annotations

import asyncio
import math
import os

import psutil

from ebrl import procenv, sizes
from ebrl.bus.peers import LivePeers, plan_admits
from ebrl.envs import EnvSpec
from ebrl.resources.nvml import GpuMonitor
from ebrl.sched.fleet import RolloutStats, make_fleet
from ebrl.sched.group import ActionExchange, SegmentOutbox, group_loop
from ebrl.sched.modes import resolve
from ebrl.sched.stepchoice import NAMES
from ebrl.service import Service, env_info, service_main


class SimService(Service):
    role = "sim"

    async def setup(self) -> None:
        cfg = self.cfg
        self.schedule = sched = resolve(cfg)
        spec = EnvSpec.from_config(cfg.env)
        info = await env_info(self)  # clear error before spawning
        bounds = self.bounds or await self.message_bounds()
        if sched.mode == "async":
            os.sched_setaffinity(0, sched.sim_cores)  # rollout's share of the machine
        if cfg.sim.nice > os.nice(0) and not self.shares_process:  # its workers take sim.nice themselves
            os.nice(cfg.sim.nice - os.nice(0))
        # sim/<instance> runs on host <instance> of a multi-host run: its groups follow the other hosts'
        share = cfg.algo.group_size if cfg.algo.name == "grpo" else 1
        # sharing a process (run.processes), GPU physics steps on its thread, in its one CUDA context
        self.fleet = make_fleet(spec, sched, host=self.instance, seed=cfg.run.seed, share=share,
                                obs_size=math.prod(info.obs_shape), inline=self.shares_process and spec.gpu_physics,
                              on_core_step=lambda core, s: self.count(f"sim/core{core}_busy_s", s),
                              on_mode=lambda mode, a, b: self.publish_span("stepping", NAMES[mode], a, b, False),
                              on_decision=self.stepping_decided)
        self.stats = RolloutStats(cfg.sim.step_timeout)
        self.fleet.stepping.timeout = self.stats.step_timeout()  # refreshed with every stats report
        self.peers = LivePeers(self.bus, self.run_name, warn=lambda: not self.stopping.is_set(),
                               admits=plan_admits(procenv.sim_hosts()))  # the iteration's length: planned hosts
        self.exchange = ActionExchange(self.bus, self.run_name, self.fleet.groups, self,
                                       action_shape=(cfg.policy.chunk, info.action_dim), layout=info.layout,
                                       max_bytes=bounds.act)
        self.outbox = SegmentOutbox(self.bus, self, cfg.train.max_pending, lambda: self.peers.has("train"),
                                    layout=info.layout)
        # a (re)started gen has none of the observations in flight: publish them again
        self.peers.on_join("gen", self.exchange.generation_restarted)
        self.peers.on_join("train", lambda: asyncio.ensure_future(self.outbox.send_held()))
        self.loops = [group_loop(g, self.fleet, self.exchange, self.outbox, self.stats, self, self.run_name, sched,
                                 cfg.sim.segment_length, lambda: self.peers.count("sim"))
                      for g in self.fleet.groups]
        psutil.cpu_percent(percpu=True)
        self.gpus = GpuMonitor()
        self.log.info("schedule: %s", sched)

    async def message_bounds(self) -> sizes.Bounds:
        """Action chunks: the run's bound (ebrl.sizes; without the policy's weights, so without torch)."""
        return sizes.of_run(self.cfg, await env_info(self), weights=False)

    async def run(self) -> None:
        while not (self.peers.has("gen") and self.peers.has("train")):  # nobody would hear us yet
            await asyncio.sleep(0.05)
        await asyncio.gather(self.publish_episodes_forever(), *(loop.run_forever() for loop in self.loops))

    async def publish_episodes_forever(self) -> None:
        while True:
            await asyncio.sleep(self.cfg.run.stats_interval)
            await self.publish_episodes()

    async def publish_episodes(self) -> None:
        """The episodes that ended since the last batch, one record each (``EpisodeBatch``), beside the stats."""
        batch = self.stats.take_episodes(self.role, self.instance)
        if batch is not None:
            await self.bus.put(self.keys.put("episodes"), batch)

    def metrics(self) -> dict[str, float]:
        self.fleet.stepping.timeout = self.stats.step_timeout()  # once per stats report, not per chunk
        out = {"sim/envs": float(self.fleet.count()),
               "sim/cores": float(len(self.cores_in_use())),  # what an allocator on another host plans with
               "sim/segments_held": float(len(self.outbox.held)), "sim/envs_given_up": float(self.fleet.given_up),
               "sim/unknown_instances": float(self.peers.unknown_seen), "sim/nice": float(os.nice(0)),
               **self.stats.metrics()}
        if (workers_nice := self.fleet.niceness()) is not None:
            out["sim/workers_nice"] = workers_nice
        if (rebinding := self.fleet.rebinding) is not None:
            out.update(rebinding.metrics())
        for core, percent in enumerate(psutil.cpu_percent(percpu=True)):
            out[f"cpu/core{core}_percent"] = percent
        out.update(self.gpus.sample())  # one sim service per host: it reports the host's GPUs
        return out

    def stepping_decided(self, text: str) -> None:
        self.log.info("stepping: %s", text)
        self.event("stepping", text)

    def cores_in_use(self) -> list[int]:
        return self.fleet.cores() or super().cores_in_use()

    def on_affinity(self, cores: list[int]) -> None:
        self.fleet.pin(cores)

    async def teardown(self) -> None:
        self.fleet.close()
        await self.publish_episodes()


def main() -> None:
    service_main(SimService)


if __name__ == "__main__":
    main()
