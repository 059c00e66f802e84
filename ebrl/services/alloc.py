"""alloc service: the elastic allocator. Reads the stages' stats, re-plans after a sustained imbalance,
pushes the new cores, threads and batch to the services (``ctl/.../{affinity,quota}``, versioned) and, on a
GPU, the stages' new shares to the launcher of its host (``ctl/<run>/launcher/<host>/gpu_share``), which
starts those stages again with them.

It runs on the host that trains and plans that host's cores. On a run over several hosts it reads every
host's simulator stats: the other hosts' simulation capacity counts toward the simulator's side of
Algorithm 1 (so the more they simulate, the fewer of this host's cores the simulator takes), and a host
that has no simulator of its own (``EBRL_LOCAL_SIM=0``, set by the launcher) gives all its cores to
generation and training. The other hosts keep their own cores (``[hosts.<name>].cores``).
"""

from __future__ import annotations

import asyncio
import time

from ebrl import procenv
from ebrl.alloc.runtime import Observations, describe, gpu_shares, make_placement, metrics_of, plan_messages
from ebrl import keys
from ebrl.messages import Affinity, StatsReport
from ebrl.service import Service, service_main

class AllocService(Service):
    role = "alloc"

    async def setup(self) -> None:
        self.local_sim = procenv.local_sim()
        # The launcher measured (or reused) the profile and started the services inside the initial plan:
        # the same file gives the same plan, which is therefore already applied.
        self.placement, path, _ = await asyncio.get_running_loop().run_in_executor(
            None, lambda: make_placement(self.cfg, measure=False, progress=False, local_sim=self.local_sim))
        self.placement.apply()
        self.log.info("profile %s; %s%s", path, describe(self.placement.applied),
                      "" if self.local_sim else " (no simulator on this host)")
        self.seen = Observations(self.instance, self.local_sim, self.cfg.run.stats_interval)
        self.rates = None
        self.stats = {role: self.bus.subscribe(self.keys.sub("stats", service=role, instance=0), StatsReport,
                                               policy="latest", capacity=4) for role in ("gen", "train")}
        self.sim_stats = self.bus.subscribe(self.keys.sub("stats", service="sim"), StatsReport, policy="latest",
                                            capacity=64)

    async def run(self) -> None:
        while True:
            _, report = await self.stats["gen"].next()  # one observation per generation report
            self.seen.stage("gen", report.metrics)
            for _, msg in self.stats["train"].drain():
                self.seen.stage("train", msg.metrics)
            now = time.monotonic()
            for key, msg in self.sim_stats.drain():
                self.seen.sim(keys.parse(key).instance, msg.metrics, now)
            if not self.seen.ready(now):
                continue
            self.rates = self.seen.rates(self.placement.applied, self.cfg.policy.chunk, self.cfg.train.batch_size)
            if self.rates is None:
                continue
            self.placement.balance(self.rates)
            self.count("alloc/observations")
            if self.placement.pending is not None:
                await self.push()

    async def push(self) -> None:
        start = time.time()
        self.placement.apply()
        plan = self.placement.applied
        for stage, instance, message in plan_messages(self.placement, self.instance, self.local_sim):
            kind = "affinity" if isinstance(message, Affinity) else "quota"
            await self.bus.put(self.keys.put(kind, service=stage, instance=instance), message)
        for share in gpu_shares(self.placement):  # the launcher restarts a stage whose share changed
            await self.bus.put(self.keys.put("gpu_share", host=self.instance), share)
        reverted = plan.reason.startswith("reverted")
        self.count("alloc/reverts" if reverted else "alloc/reallocations")
        self.publish_span("alloc", "realloc", start, time.time())
        self.event("revert" if reverted else "realloc", f"{describe(plan)}; because {plan.reason}")
        self.log.info("re-allocated: %s (%s)", describe(plan), plan.reason)

    def metrics(self) -> dict[str, float]:
        return {**metrics_of(self.placement, self.rates), "alloc/sim_hosts": float(len(self.seen.sims))}


def main() -> None:
    service_main(AllocService)


if __name__ == "__main__":
    main()
