"""gen service: batches the groups whose observations are ready, answers each with an action chunk."""

from __future__ import annotations

import asyncio
import concurrent.futures
import time

import numpy as np
import torch

from ebrl.bus import keys
from ebrl.envs import EnvSpec, spaces
from ebrl.messages import ActionChunk, MessageError, Observation, Weights, decode_message
from ebrl.policies import load_arrays, make_policy
from ebrl.service import Service, service_main


class GenService(Service):
    role = "gen"

    async def setup(self) -> None:
        cfg = self.cfg
        torch.set_num_threads(cfg.gen.threads)
        obs_space, act_space = await asyncio.get_running_loop().run_in_executor(
            None, spaces, EnvSpec.from_config(cfg.env))
        self.policy = make_policy(cfg.policy, obs_space.shape, act_space.shape[0])
        self.policy.eval()
        self.version = -1
        self.max_groups = cfg.gen.max_batch_groups or cfg.sim.groups
        # Forward passes run on one dedicated thread, never on the event loop.
        self.pool = concurrent.futures.ThreadPoolExecutor(1, thread_name_prefix="gen-forward")
        self.obs = self.bus.subscribe(keys.obs(self.run_name), Observation, capacity=4 * cfg.sim.groups)
        self.weights = self.bus.subscribe(keys.weights(self.run_name), Weights, policy="latest", capacity=1)

    async def run(self) -> None:
        await self.initial_weights()
        while True:
            first = await self.obs.next()
            batch = [first[1]] + [m for _, m in self.obs.drain(self.max_groups - 1)]
            self.apply_latest_weights()
            obs = np.concatenate([m.obs for m in batch])
            start = time.time()
            actions, logprobs, values = await asyncio.get_running_loop().run_in_executor(
                self.pool, self.policy.act, obs)
            self.publish_span("gen", "forward", start, time.time())
            row = 0
            for m in batch:
                n = len(m.env_ids)
                chunk = ActionChunk(group=m.group, seq=m.seq, policy_version=self.version,
                                    actions=actions[row:row + n], logprobs=logprobs[row:row + n],
                                    values=values[row:row + n])
                await self.bus.put(keys.act(self.run_name, m.group), chunk, express=True)
                row += n
            self.count("gen/batches")
            self.count("gen/groups_served", len(batch))
            self.count("gen/envs_served", row)

    async def initial_weights(self) -> None:
        """Ask train for its latest weights (request-reply), retrying until it answers."""
        while self.version < 0:
            self.apply_latest_weights()
            if self.version >= 0:
                return
            for key, payload in await self.bus.get(keys.weights(self.run_name), timeout=1.0):
                try:
                    self.load(decode_message(Weights, payload))
                except (MessageError, ValueError) as exc:
                    self.bus.count_malformed(key, exc)
            if self.version < 0:
                await asyncio.sleep(0.2)

    def apply_latest_weights(self) -> None:
        latest = self.weights.drain()
        if latest and latest[-1][1].version > self.version:
            self.load(latest[-1][1])

    def load(self, weights: Weights) -> None:
        load_arrays(self.policy, weights.params)
        self.version = weights.version
        self.count("gen/weights_applied")

    def metrics(self) -> dict[str, float]:
        return {"gen/policy_version": float(self.version), "gen/obs_queue": float(len(self.obs))}

    async def teardown(self) -> None:
        self.pool.shutdown(wait=False, cancel_futures=True)


def main() -> None:
    service_main(GenService)


if __name__ == "__main__":
    main()
