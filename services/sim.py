"""sim service: environment groups in worker processes; observations out, action chunks in, segments to train."""

from __future__ import annotations

import asyncio
import collections
import os
import time

import numpy as np
import psutil

from ebrl.bus import keys
from ebrl.envs import EnvSpec, EnvWorker, describe
from ebrl.envs.worker import WorkerFailed
from ebrl.messages import ActionChunk, Observation, TrajectorySegment
from ebrl.resources.nvml import GpuMonitor
from ebrl.sched.modes import resolve
from ebrl.sched.rollout import Episodes, SegmentBuilder
from ebrl.sched.stepping import BatchStepping, IndependentStepping, RebindingStepping
from ebrl.service import Service, service_main

# A group whose observation got no answer for this long publishes it again (a
# generation restart or a lost sample must never leave a group waiting forever).
ACTION_TIMEOUT_S = 30.0


class SimService(Service):
    role = "sim"

    async def setup(self) -> None:
        cfg = self.cfg
        self.schedule = sched = resolve(cfg)
        spec = EnvSpec.from_config(cfg.env)
        await asyncio.get_running_loop().run_in_executor(None, describe, spec)  # clear error before spawning
        if sched.mode == "async":
            os.sched_setaffinity(0, sched.sim_cores)  # rollout's share of the machine
        if sched.core_rebinding:
            self.stepping = RebindingStepping(sched.sim_cores, on_step=self._on_core_step)
        else:
            self.stepping = IndependentStepping() if sched.stepping == "async" else BatchStepping()
        # sim/<instance> runs on host <instance> of a multi-host run: its group and env ids follow the
        # other hosts' (group ids name bus keys, env ids seed the envs), so every one is unique in the run.
        first = self.instance * sched.groups
        self.groups = list(range(first, first + sched.groups))
        per = sched.envs_per_group
        self.episodes = Episodes(range(first * per, (first + sched.groups) * per),
                                 cfg.algo.group_size if cfg.algo.name == "grpo" else 1)
        self.workers: dict[int, list[EnvWorker]] = {}
        for g in self.groups:
            self.workers[g] = []
            for i in range(per):
                env = g * per + i
                # Static pinning round-robin over the simulation cores, unless steps are rebound one by one.
                core = None if sched.core_rebinding else sched.sim_cores[env % len(sched.sim_cores)]
                worker = EnvWorker(spec, seed=self.env_seed(env), core=core)
                self.workers[g].append(worker)
                if sched.core_rebinding:
                    self.stepping.add(env, worker)
        self.actions = {g: self.bus.subscribe(keys.act(self.run_name, g), ActionChunk, capacity=4)
                        for g in self.groups}
        self.returns: collections.deque[float] = collections.deque(maxlen=20)
        self.successes: collections.deque[bool] = collections.deque(maxlen=20)
        self.chunk_latency: collections.deque[float] = collections.deque(maxlen=1000)  # per env and chunk
        self.stepping.timeout = self.step_timeout()  # refreshed with every stats report
        self.peers_live: set[str] = set()
        # segments finished while no train was live (a restart, a new GPU share): sent when one is back
        self.held: collections.deque[tuple[str, TrajectorySegment]] = collections.deque()
        self.held_steps = 0
        self.gen_epoch = 0
        self.bus.watch_liveliness(keys.live_all(self.run_name), self._on_liveliness)
        psutil.cpu_percent(percpu=True)
        self.gpus = GpuMonitor()
        self.log.info("schedule: %s", sched)

    def _on_liveliness(self, key: str, alive: bool) -> None:
        (self.peers_live.add if alive else self.peers_live.discard)(key)
        self.log.debug("%s %s", key, "live" if alive else "gone")
        if not alive and not self.stopping.is_set():
            self.log.warning("%s left the bus", key)
        if alive and keys.role_of(key) == "gen":
            self.gen_epoch += 1  # a (re)started gen has none of the observations in flight: publish them again
        if alive and keys.role_of(key) == "train" and self.held:
            asyncio.ensure_future(self.send_held())

    async def send_segment(self, key: str, segment: TrajectorySegment) -> None:
        """Publish a finished segment, or hold it while no train is live (at most ``train.max_pending``
        decisions; beyond that the oldest are dropped, counted): training resumes where it stopped."""
        if self._role_live("train"):
            await self.send_held()
            await self.bus.put(key, segment)
            return
        self.count("sim/segments_while_train_down")
        self.held.append((key, segment))
        self.held_steps += len(segment.obs)
        while self.held_steps > self.cfg.train.max_pending:
            _, dropped = self.held.popleft()
            self.held_steps -= len(dropped.obs)
            self.count("sim/segments_dropped_train_down")

    async def send_held(self) -> None:
        while self.held and self._role_live("train"):
            key, segment = self.held.popleft()
            self.held_steps -= len(segment.obs)
            await self.bus.put(key, segment)
            self.count("sim/segments_sent_late")

    def _on_core_step(self, core: int, seconds: float) -> None:
        self.count(f"sim/core{core}_busy_s", seconds)

    def sim_hosts(self) -> int:
        return sum(1 for k in self.peers_live if keys.role_of(k) == "sim")

    def _role_live(self, role: str) -> bool:
        return any(keys.role_of(k) == role for k in self.peers_live)

    async def run(self) -> None:
        while not (self._role_live("gen") and self._role_live("train")):  # nobody would hear us yet
            await asyncio.sleep(0.05)
        await asyncio.gather(*(self.run_group(g) for g in self.groups))

    async def run_group(self, g: int) -> None:
        workers = self.workers[g]
        per = len(workers)
        env_ids = np.arange(g * per, (g + 1) * per, dtype=np.int64)
        builders = [SegmentBuilder(g, int(e), self.cfg.sim.segment_length) for e in env_ids]
        obs = np.stack(await asyncio.gather(*(w.reset() for w in workers)))
        seq = 0
        while True:
            active = [i for i in range(per) if self.episodes.may_act(int(env_ids[i]))]
            if not active:  # every env waits for GRPO group-mates in other sim groups
                await self.episodes.moved()
                continue
            chunk = await self.exchange(g, seq, env_ids, obs)
            start = time.time()
            done, latency_of = await self.stepping.run_chunk([workers[i] for i in active], chunk.actions[active])
            self.publish_span(f"sim.g{g}", "chunk", start, time.time())
            results: list = [None] * per  # None: waiting at the start of its next episode, did not act
            latencies = [0.0] * per
            for j, i in enumerate(active):
                results[i], latencies[i] = done[j], latency_of[j]
            boundary = (seq + 1) % self.schedule.length(self.sim_hosts()) == 0
            next_obs = obs.copy()
            for i, res in enumerate(results):
                env = int(env_ids[i])
                if res is None:
                    continue
                if isinstance(res, WorkerFailed):  # replaced; its episode so far is dropped, never published
                    next_obs[i] = await self.replace_worker(g, i, env, res, self.episodes.index[env] + 1)
                    self.count("sim/partial_decisions_dropped", len(builders[i]))
                    builders[i] = SegmentBuilder(g, env, self.cfg.sim.segment_length)
                    self.episodes.set(env, self.episodes.index[env] + 1)
                    continue
                self.chunk_latency.append(latencies[i])
                self.episodes.set(env, res.episode + int(res.terminated or res.truncated))
                self.count("sim/env_steps", res.steps)
                self.count("sim/step_busy_s", res.busy_s)
                if res.episode_return is not None:
                    self.returns.append(res.episode_return)
                    self.count("sim/episodes")
                if res.episode_success is not None:
                    self.successes.append(res.episode_success)
                segment = builders[i].add(obs[i], chunk.actions[i], chunk.latents[i], float(chunk.logprobs[i]),
                                          float(chunk.values[i]), chunk.policy_version, res, boundary)
                if segment is not None:
                    await self.send_segment(keys.traj(self.run_name, g), segment)
                    self.count("sim/segments")
                next_obs[i] = res.next_obs
            obs = next_obs
            seq += 1

    def env_seed(self, env: int) -> int:
        # GRPO compares rollouts from the same initial states: a group's envs share reset seeds.
        return self.cfg.run.seed * 100_003 + self.episodes.members(env)[0]

    def step_timeout(self) -> float:
        if self.cfg.sim.step_timeout > 0:
            return self.cfg.sim.step_timeout
        if len(self.chunk_latency) < 50:
            return 120.0
        return max(20.0, 20 * float(np.percentile(self.chunk_latency, 99)))

    async def replace_worker(self, g: int, i: int, env: int, failure: WorkerFailed, episode: int) -> np.ndarray:
        """Kill a dead or hung env worker, start a new one for the same env (same seed and core) and start
        episode ``episode`` there (the episode numbering, hence GRPO's groups, carries on)."""
        old = self.workers[g][i]
        self.log.warning("env %d: %s; replacing its worker (the episode in progress is dropped)", env, failure)
        self.event("worker", f"env {env}: {failure}; worker replaced")
        self.count("sim/worker_restarts")
        old.kill()
        worker = EnvWorker(EnvSpec.from_config(self.cfg.env), seed=self.env_seed(env),
                           core=old.core if not self.schedule.core_rebinding else None)
        self.workers[g][i] = worker
        if isinstance(self.stepping, RebindingStepping):
            self.stepping.replace(env, worker)
        return await worker.reset(episode)

    async def exchange(self, g: int, seq: int, env_ids: np.ndarray, obs: np.ndarray) -> ActionChunk:
        """Publish this group's observations and wait for the action chunk that answers them."""
        message = Observation(group=g, seq=seq, env_ids=env_ids, obs=obs, sent_at=time.time())
        while True:
            await self.bus.put(keys.obs(self.run_name, g), message, express=True)
            start, epoch = time.time(), self.gen_epoch
            deadline = time.monotonic() + ACTION_TIMEOUT_S
            while time.monotonic() < deadline and epoch == self.gen_epoch:
                try:
                    _, chunk = await asyncio.wait_for(self.actions[g].next(), min(1.0, deadline - time.monotonic()))
                except asyncio.TimeoutError:
                    continue
                if chunk.seq == seq and chunk.actions.shape[0] == len(env_ids) == chunk.latents.shape[0]:
                    self.publish_span(f"sim.g{g}", "wait", start, time.time(), busy=False)
                    return chunk
                self.count("sim/stale_actions_dropped")
            self.count("sim/obs_resent")
            if epoch == self.gen_epoch:
                self.log.warning("group %d: no actions for seq %d after %.0f s, publishing again", g, seq,
                                 ACTION_TIMEOUT_S)

    def metrics(self) -> dict[str, float]:
        self.stepping.timeout = self.step_timeout()  # once per stats report, not per chunk
        out = {"sim/envs": float(sum(len(w) for w in self.workers.values())),
               "sim/cores": float(len(self.cores_in_use())),  # what an allocator on another host plans with
               "sim/segments_held": float(len(self.held))}
        if self.returns:
            out["sim/episode_return_mean"] = float(np.mean(self.returns))
        if self.successes:
            out["sim/success_rate"] = float(np.mean(self.successes))
        if self.chunk_latency:
            lat = np.asarray(self.chunk_latency)
            out["sim/chunk_latency_avg_ms"] = float(lat.mean() * 1e3)
            out["sim/chunk_latency_p50_ms"] = float(np.percentile(lat, 50) * 1e3)
            out["sim/chunk_latency_p99_ms"] = float(np.percentile(lat, 99) * 1e3)
        if isinstance(self.stepping, RebindingStepping):
            out["sim/rebinds"] = float(self.stepping.rebinds)
        for core, percent in enumerate(psutil.cpu_percent(percpu=True)):
            out[f"cpu/core{core}_percent"] = percent
        out.update(self.gpus.sample())  # one sim service per host: it reports the host's GPUs
        return out

    def cores_in_use(self) -> list[int]:
        if isinstance(self.stepping, RebindingStepping):
            return sorted(self.stepping.sched.budget)
        return sorted({w.core for g in self.groups for w in self.workers[g] if w.core is not None}) \
            or super().cores_in_use()

    def on_affinity(self, cores: list[int]) -> None:
        """A new simulation core budget: rebinding uses it from the next step; static pinning re-pins."""
        if isinstance(self.stepping, RebindingStepping):
            self.stepping.set_budget(cores)
            return
        flat = [w for g in self.groups for w in self.workers[g]]
        for i, worker in enumerate(flat):
            worker.pin(cores[i % len(cores)])

    async def teardown(self) -> None:
        for workers in self.workers.values():
            for worker in workers:
                worker.close(timeout=1.0)


def main() -> None:
    service_main(SimService)


if __name__ == "__main__":
    main()
