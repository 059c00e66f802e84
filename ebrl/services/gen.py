"""gen service: batches the groups whose observations are ready, answers each with an action chunk.

Which observations a policy version may answer (the staleness bound) is ``ebrl.sched.batching``; where each
forward pass runs (the event loop or the forward thread) and how it answers each group, ``ebrl.sched.forward``.
"""

from __future__ import annotations

import asyncio
import os

import numpy as np
import torch

from ebrl import devices, meta, obswire, procenv, sizes, threads
from ebrl import graph
from ebrl.bus.peers import LivePeers, plan_admits
from ebrl.messages import Observation, Quota
from ebrl.policies import load_arrays, make_policy
from ebrl.policies.graphs import Actor
from ebrl.sched.batching import ObservationQueue
from ebrl.sched.forward import Forward, answers
from ebrl.sched.modes import resolve
from ebrl.service import Service, env_info, service_main
from ebrl.weights import WeightsLayout, WeightsReceiver, known_version


class GenService(Service):
    role = "gen"

    async def setup(self) -> None:
        cfg = self.cfg
        self.schedule = resolve(cfg)
        if self.schedule.gen_cores:
            os.sched_setaffinity(0, self.schedule.gen_cores)
        threads.set_threads(cfg.gen.threads, pool_only=True)
        info = await env_info(self)
        bounds = self.bounds or await self.message_bounds()
        self.use_device(devices.resolve(cfg.gen.device, "gen.device"))
        self.policy = make_policy(cfg.policy, info.layout, info.action_dim, info.bounds).to(self.device)
        self.policy.eval()
        self.actor = Actor(self.policy, cfg.gen.compile, cfg.policy.dtype)  # eager, or CUDA graphs per batch size
        torch.manual_seed(meta.gen_seed(cfg.run.seed, self.instance))  # the actions' sampling (every device)
        self.version = -1
        self.batch_groups = cfg.gen.max_batch_groups  # 0: every group of every live sim host
        # the sim hosts that serve: live ones of the run's plan only (a token of another instance moves nothing)
        self.sims = LivePeers(self.bus, self.run_name, "sim", warn=lambda: False,
                              admits=plan_admits(procenv.sim_hosts()))
        self.waiting = ObservationQueue(self.schedule, info.obs_shape)  # those whose iteration needs a newer policy
        self.pool = threads.TorchPool("gen-forward")  # passes and weight loads, with gen's torch threads
        self.forward = Forward(self.actor, self.device, self.pool)  # short CPU passes on the loop itself
        self.wake = asyncio.Event()
        # A group has at most one observation in flight; room for the groups of many sim hosts.
        decode = obswire.decoder(Observation, info.layout, info.obs_shape)  # camera images arrive as bytes
        self.obs = self.bus.subscribe(self.keys.sub("obs"), decode, capacity=4 * self.schedule.groups * 16,
                                      notify=self.wake, max_bytes=bounds.obs)
        # assembles off the event loop; takes only versions of this policy's tensors, finite, plausibly numbered
        self.weights = WeightsReceiver(self.bus, self.run_name, notify=self.wake,
                                       layout=WeightsLayout.of_model(self.policy), floor=known_version(self.run_dir),
                                       follow=True,  # back to train's weights if a forged version put gen ahead
                                       max_bytes=bounds.weights)

    async def message_bounds(self) -> sizes.Bounds:
        """Observations and weights: the run's bounds (ebrl.sizes), the policy's tensors included."""
        info = await env_info(self)
        return await asyncio.get_running_loop().run_in_executor(None, lambda: sizes.of_run(self.cfg, info,
                                                                                           weights=True))

    @property
    def max_groups(self) -> int:
        return self.batch_groups or self.schedule.groups * max(1, self.sims.count("sim"))

    async def run(self) -> None:
        await self.initial_weights()
        while True:
            self.wake.clear()
            await self.apply_latest_weights()
            self.waiting.extend([m for _, m in self.obs.drain()])
            batch = self.waiting.take(self.version, self.sims.count("sim"), self.max_groups)
            if not batch:
                if len(self.waiting):
                    self.count("gen/throttled")
                await self.wake.wait()  # new observations or new weights
                continue
            await self.serve(batch)

    async def serve(self, batch: list[Observation]) -> None:
        outputs, start, end = await self.forward.timed(np.concatenate([m.obs for m in batch]))
        self.publish_span("gen", "forward", start, end)
        for chunk in answers(batch, self.version, outputs):
            await self.bus.put(self.keys.put("act", group=chunk.group), chunk, express=True)
        envs = sum(len(m.env_ids) for m in batch)
        for name, n in (("gen/batches", 1), ("gen/groups_served", len(batch)), ("gen/envs_served", envs)):
            self.count(name, n)

    async def initial_weights(self) -> None:
        """Ask train for its newest weights (request-reply; a large version comes in parts), until one is here."""
        while self.version < 0:
            await self.weights.request(timeout=30.0)  # returns as soon as train has answered, or at once if none
            await self.apply_latest_weights()
            if self.version < 0:
                await asyncio.sleep(0.2)

    async def apply_latest_weights(self) -> None:
        """Swap to the newest complete weights, between batches: the load runs on the forward thread, so no
        forward pass ever sees half of it."""
        weights = self.weights.take_newer(self.version)
        if weights is None:
            return
        try:
            await asyncio.get_running_loop().run_in_executor(self.pool, load_arrays, self.policy, weights.params)
        except ValueError as exc:  # weights of another policy
            self.bus.count_malformed(graph.keys_of(self.run_name, "train").put("weights"), exc)
            self.weights.reject(weights, self.version)
            return
        if weights.version < self.version:  # back to train's from a version no trainer made (ebrl.weights)
            self.waiting.went_back(self.version, weights.version)
        self.version = weights.version
        self.count("gen/weights_applied")

    def on_quota(self, quota: Quota) -> None:
        """Threads as the base does; ``batch`` caps the envs of one forward pass (whole groups, at least one)."""
        super().on_quota(quota)
        if quota.batch:
            self.batch_groups = max(1, quota.batch // self.schedule.envs_per_group)

    def metrics(self) -> dict[str, float]:
        return {"gen/policy_version": float(self.version), "gen/obs_queue": float(len(self.obs)),
                "gen/sim_hosts": float(self.sims.count("sim")), "gen/unknown_instances": float(self.sims.unknown_seen),
                **{f"gen/{k}": float(v) for k, v in {**self.waiting.counters(), **self.weights.counters(),
                                                     **self.actor.counters()}.items()}}

    async def teardown(self) -> None:
        self.pool.shutdown(wait=False, cancel_futures=True)


def main() -> None:
    service_main(GenService)


if __name__ == "__main__":
    main()
