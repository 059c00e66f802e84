"""train service: consumes trajectory segments continuously, runs the algorithm's updates, publishes versioned weights.

The learning and its version rules are ``ebrl.algos.learner``, when it learns and checkpoints
``ebrl.algos.cycle``; with ``train.world_size`` > 1 this is one rank of a data-parallel group
(``ebrl.algos.ranks``): rank 0 talks to the run, the others learn from its shards.
"""

from __future__ import annotations

import asyncio
import os
import time
from typing import Any

from ebrl import obswire, procenv, sizes, threads
from ebrl.algos.cycle import UpdateCycle, wind_down
from ebrl.algos.handover import HANDOVER_FILE
from ebrl.algos.learner import Learner
from ebrl.algos.replaylink import connect_replay
from ebrl.algos.ranks import Ranks
from ebrl.messages import SegmentBatch, TrajectorySegment
from ebrl.runview import may_end
from ebrl.sched.modes import resolve
from ebrl.service import STOP_TO_RESTART, Service, env_info, service_main
from ebrl.weights import WeightsPublisher


class TrainService(Service):
    role = "train"

    async def setup(self) -> None:
        cfg, loop = self.cfg, asyncio.get_running_loop()
        rank, world, schedule = self.instance, cfg.train.world_size, resolve(cfg)
        if cores := schedule.train_cores:  # ranks share the training cores: each its own slice when there are enough
            os.sched_setaffinity(0, cores[rank::world] if len(cores) >= world else cores)
        threads.set_threads(cfg.train.threads, pool_only=True)
        info = await env_info(self)
        self.learner = learner = Learner(cfg, info, schedule.max_staleness, self, self.run_dir, rank, world)
        self.use_device(learner.device)
        if cfg.policy.checkpoint:
            self.log.info("policy initialised from %s", cfg.policy.checkpoint)
            self.event("checkpoint", f"policy initialised from {cfg.policy.checkpoint}")
        if resumed := learner.resume(procenv.version_floor()):  # every rank starts from the same checkpoint
            self.event("resumed", resumed)
        self.pool = threads.TorchPool("train-update")  # updates run with train's torch threads
        self.ranks: Ranks | None = None
        if world > 1:  # waits until every rank joined; every rank starts from rank 0's weights
            await loop.run_in_executor(None, learner.join)
            self.ranks = Ranks(learner, self.pool)
            self.log.info("rank %d of %d joined the training group (%s)", rank, world, cfg.train.parallel)
        self.last: dict[str, float] = {}
        if rank > 0:
            return
        bounds = self.bounds or await self.message_bounds()
        decode = obswire.decoder(TrajectorySegment, info.layout, info.obs_shape)  # camera images arrive as bytes
        self.traj = self.bus.subscribe(self.keys.sub("traj"), decode, capacity=256, max_bytes=bounds.traj)
        self.packed = self.bus.subscribe(self.keys.sub("packed"),  # vectorized groups' segments, packed
                                         obswire.decoder(SegmentBatch, info.layout, info.obs_shape), capacity=32,
                                         max_bytes=bounds.packed)
        self.weights = WeightsPublisher(self.bus, self.run_name)  # also answers late joiners with the newest
        # an off-policy algorithm's minibatches come from the replay service
        self.replay = connect_replay(self.bus, cfg, info, learner.algo, self.count, bounds.replay_sample)
        taken, handed = learner.take_over(lambda exc: self.bus.count_malformed(os.path.join(self.run_dir,
                                                                                            HANDOVER_FILE), exc))
        if handed:  # by the train before this one (a new GPU share)
            self.log.info("took over %d of %d segments handed over", taken, handed)
        self.cycle = UpdateCycle(learner, self.pool, self.ranks)

    async def message_bounds(self) -> sizes.Bounds:  # segments, one by one and packed; the replay's minibatches
        return sizes.of_run(self.cfg, await env_info(self), weights=False)

    async def run(self) -> None:
        if self.instance > 0:
            while await self.ranks.follow_one(self.learned):
                pass
            self.log.info("idle until stopped")
            return await self.stopping.wait()
        receiver = asyncio.create_task(self.receive())
        try:
            await self.publish_weights()
            await asyncio.get_running_loop().run_in_executor(self.pool, self.learner.algo.prepare)
            while self.cfg.run.iterations == 0 or self.learner.version < self.cfg.run.iterations:
                if not (items := await self.cycle.next_items()):  # too stale, or a keep-alive to the other ranks
                    continue
                start = time.time()
                losses = await asyncio.get_running_loop().run_in_executor(self.pool, self.learner.update, items)
                self.learned(losses, start)
                await self.publish_weights()
                if may_end(self.cfg.run, self.learner.version, self.learner.intake.metrics()):
                    await self.publish_stats()  # the launcher ends the run on this report, not an interval later
                await self.cycle.checkpoint(self.run_name)
            self.log.info("reached run.iterations = %d; idle until stopped", self.cfg.run.iterations)
            if self.ranks:
                await self.ranks.stop()
            await self.stopping.wait()
        finally:
            receiver.cancel()

    def learned(self, losses: dict[str, float], start: float) -> None:
        self.publish_span("train", "update" if self.instance == 0 else f"update.r{self.instance}", start, time.time())
        self.last = {f"train/{k}": v for k, v in losses.items()}
        if self.instance == 0:
            self.last["train/update_s"] = time.time() - start
        self.count("train/updates")

    async def receive(self) -> None:
        """Drain trajectories all the time (also during updates) into the learner's bounded collector."""
        async def drain(subscription: Any) -> None:
            async for key, msg in subscription:
                self.accept(key, msg)
        replay = [self.replay.receive()] if self.replay else []  # the replay's answers (an off-policy algorithm's)
        await asyncio.gather(drain(self.traj), drain(self.packed), *replay)

    def accept(self, key: str, msg: TrajectorySegment | SegmentBatch) -> None:
        self.cycle.accept(msg, lambda exc: self.bus.count_malformed(key, exc))

    async def publish_weights(self) -> None:
        """Send the weights the update thread took; packing and sending run on the publisher's thread."""
        start = time.time()
        stats = await self.weights.publish(self.learner.version, self.learner.arrays, created_at=start)
        self.publish_span("weights", f"v{self.learner.version}", start, time.time())
        self.count("train/weights_published")
        self.last["train/weights_publish_s"] = stats.pack_s + stats.send_s

    def metrics(self) -> dict[str, float]:
        queue = {"train/traj_queue": float(len(self.traj))} if self.instance == 0 else {}
        return {**self.learner.metrics(), **self.last, **queue}

    async def teardown(self) -> None:
        await wind_down(self.learner, self.pool, self.ranks)  # the other ranks released, an update in flight ended
        if self.instance > 0:
            return
        self.weights.close()
        if self.stop_reason == STOP_TO_RESTART:  # the next train takes over (a run that ends keeps nothing)
            for key, msg in [*self.traj.drain(), *self.packed.drain()]:  # what arrived while stopping
                self.accept(key, msg)
            if n := self.learner.hand_over():
                self.log.info("handed over %d segments not yet trained on (%s)", n, HANDOVER_FILE)
        if path := self.learner.save_at_end(self.run_name):
            self.log.info("policy v%d saved to %s", self.learner.version, path)


def main() -> None:
    service_main(TrainService)


if __name__ == "__main__":
    main()
