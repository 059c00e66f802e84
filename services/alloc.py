"""alloc service: the elastic allocator. Reads the stages' stats, re-plans after a sustained imbalance,
pushes the new cores, threads and batch to the services (``ctl/.../{affinity,quota}``, versioned)."""

from __future__ import annotations

import asyncio
import time

from ebrl.alloc.runtime import capacities, describe, make_placement, metrics_of
from ebrl.bus import keys
from ebrl.messages import Affinity, Quota, StatsReport
from ebrl.service import Service, service_main


class AllocService(Service):
    role = "alloc"

    async def setup(self) -> None:
        # The launcher measured (or reused) the profile and started the services inside the initial plan:
        # the same file gives the same plan, which is therefore already applied.
        self.placement, path, _ = await asyncio.get_running_loop().run_in_executor(
            None, lambda: make_placement(self.cfg, measure=False, progress=False))
        self.placement.apply()
        self.log.info("profile %s; %s", path, describe(self.placement.applied))
        self.latest: dict[str, dict[str, float]] = {}
        self.rates = None
        self.stats = {role: self.bus.subscribe(keys.stats(self.run_name, role, 0), StatsReport, policy="latest",
                                               capacity=4) for role in ("sim", "gen", "train")}

    async def run(self) -> None:
        while True:
            _, report = await self.stats["sim"].next()  # one observation per sim report
            for role, sub in self.stats.items():
                for _, msg in sub.drain():
                    self.latest[role] = msg.metrics
            self.latest["sim"] = report.metrics
            if len(self.latest) < 3:
                continue
            plan = self.placement.applied
            self.rates = capacities(self.latest["sim"], self.latest["gen"], self.latest["train"],
                                    chunk=self.cfg.policy.chunk, batch_size=self.cfg.train.batch_size,
                                    cores={stage: len(c) for stage, c in plan.cores.items()})
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
        for stage in ("sim", "gen", "train"):
            await self.bus.put(keys.ctl(self.run_name, stage, 0, "affinity"),
                               Affinity(version=plan.version, cores=plan.cores[stage]))
            if stage != "sim":
                await self.bus.put(keys.ctl(self.run_name, stage, 0, "quota"), Quota(
                    version=plan.version, threads=plan.threads[stage],
                    batch=plan.gen_batch if stage == "gen" else None))
        reverted = plan.reason.startswith("reverted")
        self.count("alloc/reverts" if reverted else "alloc/reallocations")
        self.publish_span("alloc", "realloc", start, time.time())
        self.event("revert" if reverted else "realloc", f"{describe(plan)}; because {plan.reason}")
        self.log.info("re-allocated: %s (%s)", describe(plan), plan.reason)

    def metrics(self) -> dict[str, float]:
        return metrics_of(self.placement, self.rates)


def main() -> None:
    service_main(AllocService)


if __name__ == "__main__":
    main()
