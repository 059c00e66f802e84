"""train service: consumes trajectory segments continuously, runs PPO updates, publishes versioned weights."""

from __future__ import annotations

import asyncio
import collections
import concurrent.futures
import os
import time

import numpy as np
import torch

from ebrl.algos import checkpoint
from ebrl.algos.grpo import GroupCollector
from ebrl.algos.ppo import PPO, SegmentCollector
from ebrl.bus import keys
from ebrl.envs import EnvSpec, describe
from ebrl.messages import TrajectorySegment, Weights, encode_message
from ebrl.policies import make_policy, save_checkpoint, state_arrays
from ebrl.sched.modes import resolve
from ebrl.service import Service, service_main


POLICY_FILE = "policy.safetensors"


class TrainService(Service):
    role = "train"

    async def setup(self) -> None:
        cfg = self.cfg
        self.schedule = resolve(cfg)
        if self.schedule.train_cores:
            os.sched_setaffinity(0, self.schedule.train_cores)
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
        self.resume()
        collector = GroupCollector if cfg.algo.name == "grpo" else SegmentCollector
        self.collector = collector(cfg.algo, cfg.train.max_pending, self.schedule.max_staleness, self.count)
        self.enough = asyncio.Event()
        self.last: dict[str, float] = {}
        self.returns: collections.deque[float] = collections.deque(maxlen=20)
        self.staleness_hist = np.zeros(self.schedule.max_staleness + 1, dtype=np.int64)  # decisions per lag
        self.pool = concurrent.futures.ThreadPoolExecutor(1, thread_name_prefix="train-update")
        self.traj = self.bus.subscribe(keys.traj(self.run_name), TrajectorySegment, capacity=256)
        self.encoded_weights = self.encode_weights()

        async def latest_weights(_: bytes) -> bytes:
            return self.encoded_weights

        self.bus.declare_queryable(keys.weights(self.run_name), latest_weights)

    def encode_weights(self) -> bytes:
        return encode_message(Weights(version=self.version, params=state_arrays(self.model), created_at=time.time()))

    async def run(self) -> None:
        receiver = asyncio.create_task(self.receive())
        try:
            await self.publish_weights()
            while self.cfg.run.iterations == 0 or self.version < self.cfg.run.iterations:
                await self.enough.wait()
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
            await self.stopping.wait()
        finally:
            receiver.cancel()

    async def receive(self) -> None:
        """Drain trajectories all the time (also during updates) into the algorithm's bounded collector."""
        async for key, seg in self.traj:
            n = len(seg.obs)
            if seg.obs.shape[1:] != self.obs_shape or seg.actions.shape[1:] != self.action_shape \
                    or seg.latents.shape[1:] != self.latent_shape \
                    or not 0 < n == len(seg.actions) == len(seg.latents) == len(seg.rewards) == len(seg.versions):
                self.bus.count_malformed(key, ValueError("segment shapes do not match the policy"))
                continue
            if int(seg.versions.max()) > self.version:  # acted by weights this train never published
                self.count("train/future_version_dropped")
                continue
            self.collector.add(seg)
            self.returns.extend(seg.episode_returns)
            self.count("train/segments_received")
            if self.collector.ready_steps >= self.cfg.train.batch_size:
                self.enough.set()

    def update(self, items: list) -> dict[str, float]:
        """One update (runs on the update thread)."""
        batch = self.collector.build(items, self.model)
        staleness = self.version - batch.versions
        self.staleness_hist += np.bincount(staleness, minlength=len(self.staleness_hist))[:len(self.staleness_hist)]
        out = self.ppo.update(batch)
        out.update(staleness_mean=float(staleness.mean()), staleness_max=float(staleness.max()),
                   batch_size=float(len(batch)))
        return out

    async def publish_weights(self) -> None:
        """Encode the current weights once: published now, and served to late joiners by the queryable."""
        start = time.time()
        self.encoded_weights = self.encode_weights()
        await self.bus.put_bytes(keys.weights(self.run_name), self.encoded_weights)
        self.publish_span("weights", f"v{self.version}", start, time.time())
        self.count("train/weights_published")

    def metrics(self) -> dict[str, float]:
        out = {"train/policy_version": float(self.version), "train/pending_steps": float(self.collector.pending_steps),
               "train/traj_queue": float(len(self.traj)), **self.last}
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
        floor = int(os.environ.get(checkpoint.VERSION_FLOOR_VAR, "-1"))
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
        start = time.time()
        path = checkpoint.save(self.run_dir, self.model, self.ppo.optimizer, self.version,
                               {"ppo": self.ppo.generator}, {"run": self.run_name})
        self.saved_version = self.version
        self.publish_span("train", "checkpoint", start, time.time())
        self.count("train/checkpoints")
        self.log.debug("checkpoint %s", path)

    async def teardown(self) -> None:
        self.pool.shutdown(wait=True, cancel_futures=True)
        if self.version > 0:
            self.save_checkpoint()
        if self.version > 0:  # the trained policy, for `--set policy.checkpoint=RUN_DIR/policy.safetensors`
            path = os.path.join(self.run_dir, POLICY_FILE)
            save_checkpoint(self.model, path, {"run": self.run_name, "version": str(self.version)})
            self.log.info("policy v%d saved to %s", self.version, path)


def main() -> None:
    service_main(TrainService)


if __name__ == "__main__":
    main()
