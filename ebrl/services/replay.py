"""replay service: the transitions an off-policy algorithm learns from (``algo.name = "sac"``), beside training.

Training sends each update's new transitions with a request for minibatches (``ebrl/data/<run>/replay/request``,
``ebrl.algos.replaylink``); this service adds them to its ring (``ebrl.algos.replay.ReplayStore``:
``replay.capacity`` transitions, within ``replay.max_bytes`` and 80 % of the host's available memory), draws the
minibatches uniformly and answers on ``.../replay/sample``. Where it runs is placement (``run.processes``): by
default it shares train's process, where both messages are handed over by reference (docs/processes.md).

With ``replay.save`` it writes its contents durably to ``RUN_DIR/replay.npz`` at most every
``replay.save_every_s`` and as it stops, and reads them back when it starts again (after a kill -9, a crash);
what training saw it take in beyond what came back is counted in ``replay/lost``, never dropped silently.
"""

from __future__ import annotations

import asyncio
import concurrent.futures
import os
import time

from ebrl import sizes
from ebrl.algos.replay import REPLAY_FILE, ReplayStore, batches_per_sample, replay_bound
from ebrl.messages import ReplayRequest
from ebrl.service import Service, env_info, service_main


class ReplayService(Service):
    role = "replay"

    async def setup(self) -> None:
        cfg, info = self.cfg, await env_info(self)
        action_size = cfg.policy.chunk * info.action_dim
        per_sample = batches_per_sample(cfg.replay.batch_size, info.layout.size, action_size)
        self.store = ReplayStore(info.layout.size, action_size, cfg.replay.capacity,
                                 replay_bound(cfg.replay.max_bytes), cfg.run.seed, per_sample * cfg.replay.batch_size)
        self.log.info("replay of %d transitions (%.1f MiB)", cfg.replay.capacity, self.store.buffer.nbytes / 2**20)
        self.path = os.path.join(self.run_dir, REPLAY_FILE)
        self.pool = concurrent.futures.ThreadPoolExecutor(1, thread_name_prefix="replay")  # requests, saves: in turn
        if cfg.replay.save and os.path.exists(self.path):
            try:
                restored = self.store.restore(self.path)
            except (ValueError, OSError, KeyError) as exc:
                self.log.warning("replay: %s unreadable (%s); starting empty", self.path, exc)
                self.event("replay", f"replay: {self.path} unreadable; what it held is counted lost")
            else:
                self.log.info("replay restored: %d transitions from %s", restored, self.path)
                self.event("replay", f"replay restored: {restored} transitions from {self.path}")
        self.lost_at_start, self.saved_at = self.store.lost, time.monotonic()
        self.rates = (time.monotonic(), self.store.buffer.inserted, self.store.sampled)
        bounds = self.bounds or await self.message_bounds()
        self.requests = self.bus.subscribe(self.keys.sub("request"), ReplayRequest, capacity=8,
                                           max_bytes=bounds.replay_request)

    async def message_bounds(self) -> sizes.Bounds:
        return sizes.of_run(self.cfg, await env_info(self), weights=False)

    async def run(self) -> None:
        loop, sample_key = asyncio.get_running_loop(), self.keys.put("sample")
        async for key, request in self.requests:
            start = time.time()
            try:
                sample = await loop.run_in_executor(self.pool, self.store.exchange, request)
            except ValueError as exc:  # transitions of other sizes than this replay's: dropped, counted
                self.bus.count_malformed(key, exc)
                continue
            await self.bus.put(sample_key, sample)
            self.publish_span("replay", f"sample {request.batches}", start, time.time())
            self.count("replay/requests")
            if self.store.lost > self.lost_at_start:
                self.lost_found()
            if self.cfg.replay.save and time.monotonic() - self.saved_at >= self.cfg.replay.save_every_s:
                await loop.run_in_executor(self.pool, self.save)

    def lost_found(self) -> None:
        """A restart's first request showed what training saw this replay take in and it no longer has."""
        lost, self.lost_at_start = self.store.lost - self.lost_at_start, self.store.lost
        why = "since its last save" if os.path.exists(self.path) else "replay.save is off" if not \
            self.cfg.replay.save else f"{self.path} is missing"
        self.log.warning("replay: %d transitions training saw it hold are lost (%s)", lost, why)
        self.event("replay", f"replay lost {lost} transitions ({why})")

    def save(self) -> None:
        """The whole replay, durably (a full 1,000,000 transitions of HalfCheetah are about 180 MB)."""
        start = time.time()
        self.store.save(self.path)
        self.saved_at = time.monotonic()
        self.publish_span("replay", "save", start, time.time())
        self.count("replay/saves")

    def metrics(self) -> dict[str, float]:
        store, now = self.store, time.monotonic()
        then, inserted0, sampled0 = self.rates
        inserted, sampled = store.buffer.inserted, store.sampled
        self.rates, dt = (now, inserted, sampled), max(now - then, 1e-9)
        return {"replay/size": float(store.buffer.size), "replay/capacity": float(store.buffer.capacity),
                "replay/bytes": float(store.buffer.nbytes), "replay/inserted": float(inserted),
                "replay/sampled": float(sampled), "replay/insert_rate": (inserted - inserted0) / dt,
                "replay/sample_rate": (sampled - sampled0) / dt, "replay/lost": float(store.lost)}

    async def teardown(self) -> None:
        if self.cfg.replay.save:  # the last request answered, the contents as the run ends or the replay stops
            await asyncio.get_running_loop().run_in_executor(self.pool, self.save)
        self.pool.shutdown(wait=True)


def main() -> None:
    service_main(ReplayService)


if __name__ == "__main__":
    main()
