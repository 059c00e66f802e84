"""train service: consumes trajectory segments continuously, runs PPO updates, publishes versioned weights.

With ``train.world_size`` > 1 this is one rank of a data-parallel group (``ebrl.algos.parallel``): rank 0
talks to the run, the other ranks only learn from the shards rank 0 scatters to them."""

from __future__ import annotations

import asyncio
import collections
import concurrent.futures
import contextlib
import os
import time

import msgpack
import numpy as np
import torch

from ebrl import procenv
from ebrl.algos import checkpoint
from ebrl.algos.grpo import GroupCollector
from ebrl.algos.parallel import KEEPALIVE_S, Command, DataParallel, shards
from ebrl.algos.ppo import PPO, Batch, SegmentCollector
from ebrl.bus import keys
from ebrl.envs import EnvSpec, describe
from ebrl.messages import TrajectorySegment, decode_message, encode_message
from ebrl.policies import make_policy, save_checkpoint, state_arrays
from ebrl.sched.modes import resolve
from ebrl.service import STOP_TO_RESTART, Service, service_main
from ebrl.weights import WeightsPublisher


POLICY_FILE = "policy.safetensors"
HANDOVER_FILE = "train-pending.msgpack"  # segments a stopping train leaves to the next one (RUN_DIR)


class TrainService(Service):
    role = "train"

    async def setup(self) -> None:
        cfg = self.cfg
        self.schedule = resolve(cfg)
        self.rank, self.world = self.instance, cfg.train.world_size
        cores = self.schedule.train_cores
        if cores:  # ranks share the training cores: each its own slice when there are enough
            os.sched_setaffinity(0, cores[self.rank::self.world] if len(cores) >= self.world else cores)
        torch.manual_seed(cfg.run.seed)
        torch.set_num_threads(cfg.train.threads)
        info = await asyncio.get_running_loop().run_in_executor(None, describe, EnvSpec.from_config(cfg.env))
        self.obs_shape = info.obs_shape
        self.action_shape = (cfg.policy.chunk, info.action_dim)
        self.model = make_policy(cfg.policy, info.layout, info.action_dim)
        self.latent_shape = tuple(self.model.latent_shape)
        if cfg.policy.checkpoint:
            self.log.info("policy initialised from %s", cfg.policy.checkpoint)
            self.event("checkpoint", f"policy initialised from {cfg.policy.checkpoint}")
        self.ppo = PPO(self.model, cfg.algo, cfg.train.lr, seed=cfg.run.seed)
        self.version = 0
        self.saved_version = -1
        self.ranks_stopped = False  # rank 0 sent (or, on ranks > 0, received) the stop command
        self.receiving: concurrent.futures.Future | None = None
        self.resume()  # every rank starts from the same checkpoint
        self.arrays = state_arrays(self.model)  # the full weights rank 0 publishes
        self.train_state: tuple[int, dict, dict] | None = None  # sharded: (version, model, optimizer) gathered
        self.dp: DataParallel | None = None
        if self.world > 1:  # waits until every rank joined; every rank starts from rank 0's weights
            self.dp = await asyncio.get_running_loop().run_in_executor(
                None, lambda: DataParallel(self.model, self.ppo.optimizer, self.rank, self.world,
                                           shard=cfg.train.parallel == "fsdp"))
            self.ppo.net, self.ppo.optimizer = self.dp.net, self.dp.optimizer
            self.log.info("rank %d of %d joined the training group (%s)", self.rank, self.world, cfg.train.parallel)
        collector = GroupCollector if cfg.algo.name == "grpo" else SegmentCollector
        self.collector = collector(cfg.algo, cfg.train.max_pending, self.schedule.max_staleness, self.count)
        self.enough = asyncio.Event()
        self.last: dict[str, float] = {}
        self.returns: collections.deque[float] = collections.deque(maxlen=20)
        self.staleness_hist = np.zeros(self.schedule.max_staleness + 1, dtype=np.int64)  # decisions per lag
        self.pool = concurrent.futures.ThreadPoolExecutor(1, thread_name_prefix="train-update")
        if self.rank > 0:
            return
        self.traj = self.bus.subscribe(keys.traj(self.run_name), TrajectorySegment, capacity=256)
        self.weights = WeightsPublisher(self.bus, self.run_name)  # also answers late joiners with the newest
        self.take_over()

    @property
    def sharded(self) -> bool:
        return self.dp is not None and self.dp.shard

    async def run(self) -> None:
        if self.rank > 0:
            return await self.follow()
        receiver = asyncio.create_task(self.receive())
        loop = asyncio.get_running_loop()
        try:
            await self.publish_weights()
            while self.cfg.run.iterations == 0 or self.version < self.cfg.run.iterations:
                if self.dp is None:
                    await self.enough.wait()
                else:
                    try:
                        await asyncio.wait_for(self.enough.wait(), KEEPALIVE_S)
                    except asyncio.TimeoutError:  # the other ranks wait in a collective: tell them to go on
                        await loop.run_in_executor(self.pool, self.dp.send, Command("idle"))
                        continue
                items = self.collector.take(self.version, self.cfg.train.batch_size)
                if self.collector.ready_steps < self.cfg.train.batch_size:
                    self.enough.clear()
                if not items:  # everything pending was too stale
                    continue
                start = time.time()
                losses = await asyncio.get_running_loop().run_in_executor(self.pool, self.update, items)
                self.publish_span("train", "update", start, time.time())
                self.version += 1
                self.last = {f"train/{k}": v for k, v in losses.items()}
                self.last["train/update_s"] = time.time() - start
                self.count("train/updates")
                await self.publish_weights()
                every = self.cfg.train.checkpoint_every
                if every and self.version % every == 0:
                    await asyncio.get_running_loop().run_in_executor(self.pool, self.save_checkpoint)
            self.log.info("reached run.iterations = %d; idle until stopped", self.cfg.run.iterations)
            await self.stop_ranks()
            await self.stopping.wait()
        finally:
            receiver.cancel()

    async def follow(self) -> None:
        """Ranks > 0: learn from the shards rank 0 scatters until it says stop."""
        while await self.follow_one():
            pass
        self.log.info("rank 0 said stop; idle until stopped")
        await self.stopping.wait()

    async def follow_one(self) -> bool:
        """Ranks > 0: carry out rank 0's next command; False once it said stop. A command being received
        when the task is cancelled is kept for the next call (``teardown`` drains up to the stop)."""
        if self.receiving is None or self.receiving.cancelled():
            self.receiving = self.pool.submit(self.dp.receive)
        command = await asyncio.wrap_future(self.receiving)
        self.receiving = None
        loop = asyncio.get_running_loop()
        if command.kind == "stop" and self.sharded:  # rank 0 gathers the final training state: take part
            await loop.run_in_executor(self.pool, self.dp.checkpoint_state)
        if command.kind == "update":
            start = time.time()
            losses = await loop.run_in_executor(self.pool, self.learn, command.items)
            self.publish_span("train", f"update.r{self.rank}", start, time.time())
            self.version += 1
            self.last = {f"train/{k}": v for k, v in losses.items()}
            self.count("train/updates")
        self.ranks_stopped = command.kind == "stop"
        return not self.ranks_stopped

    async def stop_ranks(self) -> None:
        """Rank 0: release the other ranks from their collective (once); they may be gone (a crash): give up
        after a few seconds."""
        if self.dp is not None and not self.ranks_stopped:
            self.ranks_stopped = True
            try:
                await asyncio.wait_for(asyncio.to_thread(self.dp.send, Command("stop")), 5.0)
                if self.sharded:  # the final training state, gathered with the others
                    state = await asyncio.wait_for(asyncio.to_thread(self.dp.checkpoint_state), 30.0)
                    self.train_state = (self.version, *state)
            except (asyncio.TimeoutError, RuntimeError) as exc:
                self.log.warning("could not stop the other training ranks cleanly: %r", exc)

    async def receive(self) -> None:
        """Drain trajectories all the time (also during updates) into the algorithm's bounded collector."""
        async for key, seg in self.traj:
            self.accept(key, seg)

    def accept(self, key: str, seg: TrajectorySegment) -> bool:
        """Check one segment and add it to the collector (False: dropped, counted)."""
        n = len(seg.obs)
        if seg.obs.shape[1:] != self.obs_shape or seg.actions.shape[1:] != self.action_shape \
                or seg.latents.shape[1:] != self.latent_shape \
                or not 0 < n == len(seg.actions) == len(seg.latents) == len(seg.rewards) == len(seg.versions):
            self.bus.count_malformed(key, ValueError("segment shapes do not match the policy"))
            return False
        if int(seg.versions.max()) > self.version:  # acted by weights this train never published
            self.count("train/future_version_dropped")
            return False
        self.collector.add(seg)
        self.returns.extend(seg.episode_returns)
        self.count("train/segments_received")
        if self.collector.ready_steps >= self.cfg.train.batch_size:
            self.enough.set()
        return True

    def hand_over(self) -> None:
        """On a stop to start again (a new GPU share): the segments received and not yet trained on, for the
        next train of this run to take over, with the checkpoint."""
        for key, seg in self.traj.drain():  # what arrived while stopping
            self.accept(key, seg)
        segments = self.collector.segments()
        if segments:
            path = os.path.join(self.run_dir, HANDOVER_FILE)
            with open(path + ".tmp", "wb") as fh:
                fh.write(msgpack.packb([encode_message(seg) for seg in segments]))
            os.replace(path + ".tmp", path)
            self.log.info("handed over %d segments not yet trained on (%s)", len(segments), path)

    def take_over(self) -> None:
        """Take over what the train before handed over (and remove it, so that it is taken once)."""
        path = os.path.join(self.run_dir, HANDOVER_FILE)
        if not os.path.exists(path):
            return
        with open(path, "rb") as fh:
            payloads = msgpack.unpackb(fh.read())
        os.remove(path)
        taken = sum(self.accept(path, decode_message(TrajectorySegment, p)) for p in payloads)
        self.log.info("took over %d of %d segments handed over", taken, len(payloads))
        self.count("train/segments_taken_over", taken)

    def update(self, items: list) -> dict[str, float]:
        """One update (runs on the update thread); with several ranks, rank 0 keeps the first shard."""
        if self.dp is not None:
            parts = shards(items, self.collector.size, self.world)
            items = self.dp.send([Command("update", part) for part in parts]).items
        return self.learn(items)

    def learn(self, items: list) -> dict[str, float]:
        """The gradient steps on this rank's items, then ``sync``; a rank without items steps with zero
        gradients. Every rank makes the same collective calls in the same order, items or not."""
        with self.dp.gathered() if self.dp is not None else contextlib.nullcontext():
            batch = self.collector.build(items, self.model) if items else None
        if self.model.obs_norm is not None:  # before the gradient steps, the same statistics on every rank
            sums = self.model.obs_norm.sums(batch.obs if batch is not None else torch.zeros(0, *self.obs_shape))
            self.model.obs_norm.merge(sums if self.dp is None else self.dp.all_sum(sums))
        if batch is None:
            out = {**self.ppo.update(self.empty_batch(), scale=0.0), "batch_size": 0.0}
        else:
            staleness = self.version - batch.versions
            self.staleness_hist += np.bincount(staleness, minlength=len(self.staleness_hist))[:len(self.staleness_hist)]
            out = self.ppo.update(batch, version=self.version)
            out.update(staleness_mean=float(staleness.mean()), staleness_max=float(staleness.max()),
                       batch_size=float(len(batch)))
        self.sync(self.version + 1)
        return out

    def sync(self, version: int) -> None:
        """After the update that makes ``version``: the full weights for rank 0 to publish and, when a
        checkpoint is due, the training state (sharded, both are collectives on every rank)."""
        if not self.sharded:
            if self.rank == 0:
                self.arrays = state_arrays(self.model)
            return
        self.arrays = self.dp.full_arrays()
        every = self.cfg.train.checkpoint_every
        if every and version % every == 0:
            self.train_state = (version, *self.dp.checkpoint_state())

    def empty_batch(self) -> Batch:
        """Zeros shaped like a batch of ``algo.minibatches`` decisions (for ``scale = 0`` steps)."""
        n = self.cfg.algo.minibatches
        zeros = torch.zeros(n)
        return Batch(obs=torch.zeros(n, *self.obs_shape), actions=torch.zeros(n, *self.action_shape),
                     latents=torch.zeros(n, *self.latent_shape), logprobs=zeros, advantages=zeros, returns=zeros,
                     values=zeros, versions=np.full(n, self.version))

    async def publish_weights(self) -> None:
        """Send the weights ``sync`` took on the update thread; packing and sending (in parts when large) run on
        the publisher's thread, never on the event loop."""
        start = time.time()
        stats = await self.weights.publish(self.version, self.arrays, created_at=start)
        self.publish_span("weights", f"v{self.version}", start, time.time())
        self.count("train/weights_published")
        self.last["train/weights_publish_s"] = stats.pack_s + stats.send_s

    def metrics(self) -> dict[str, float]:
        out = {"train/policy_version": float(self.version), **self.last}
        if self.rank > 0:
            return out
        out.update({"train/pending_steps": float(self.collector.pending_steps), "train/traj_queue": float(len(self.traj))})
        if self.returns:
            out["train/episode_return_mean"] = float(np.mean(self.returns))
        for lag, n in enumerate(self.staleness_hist):
            out[f"train/staleness_hist_{lag}"] = float(n)
        return out

    def resume(self) -> None:
        """Carry on from the run's latest checkpoint, if any (a restart after a crash, or ``ebrl up --resume``).
        Versions never go back or repeat: after a crash the launcher passes the newest version anyone saw
        (EBRL_VERSION_FLOOR), which may be past the checkpoint; the restored weights then get the next one."""
        found = checkpoint.latest(self.run_dir)
        if found is not None:
            restored = checkpoint.restore(found, self.model, self.ppo.optimizer, {"ppo": self.ppo.generator})
            self.version = self.saved_version = restored.version
            self.log.info("resumed from %s (policy v%d)", found, restored.version)
        floor = procenv.version_floor()
        if floor >= self.version and floor > 0:
            self.log.warning("versions up to v%d were published before the restart; the %s weights continue as "
                             "v%d", floor, f"v{self.version}" if found else "initial", floor + 1)
            self.version = floor + 1
        if found is not None or floor > 0:
            self.event("resumed", f"train resumed at policy v{self.version}"
                                  + (f" from {found.name}" if found is not None else " with fresh weights"))

    def save_checkpoint(self) -> None:
        """Write the training state (runs on the update thread, between updates)."""
        if self.version == self.saved_version:
            return
        model_state, optimizer = None, self.ppo.optimizer
        if self.sharded:  # what the ranks gathered (sync, stop_ranks)
            if self.train_state is None or self.train_state[0] != self.version:
                return
            _, model_state, optimizer = self.train_state
        start = time.time()
        path = checkpoint.save(self.run_dir, self.model, optimizer, self.version,
                               {"ppo": self.ppo.generator}, {"run": self.run_name}, model_state=model_state)
        self.saved_version = self.version
        self.publish_span("train", "checkpoint", start, time.time())
        self.count("train/checkpoints")
        self.log.debug("checkpoint %s", path)

    async def teardown(self) -> None:
        if self.rank > 0:  # finish what rank 0 started, up to its stop
            with contextlib.suppress(RuntimeError):  # rank 0 is gone: the collective failed
                while self.dp is not None and not self.ranks_stopped and await self.follow_one():
                    pass
        await asyncio.to_thread(self.pool.shutdown, wait=True, cancel_futures=True)  # an update in flight ends
        if self.rank == 0:
            await self.stop_ranks()
        if self.dp is not None:
            self.dp.close()
        if self.rank > 0:
            return
        self.weights.close()
        if self.stop_reason == STOP_TO_RESTART:  # the next train takes over (a run that ends keeps nothing)
            self.hand_over()
        if self.version > 0:
            self.save_checkpoint()
            # the trained policy, for `--set policy.checkpoint=RUN_DIR/policy.safetensors`
            path = os.path.join(self.run_dir, POLICY_FILE)
            weights = {name: torch.from_numpy(a) for name, a in self.arrays.items()}  # full, also when sharded
            save_checkpoint(self.model, path, {"run": self.run_name, "version": str(self.version)}, state=weights)
            self.log.info("policy v%d saved to %s", self.version, path)


def main() -> None:
    service_main(TrainService)


if __name__ == "__main__":
    main()
