"""The group pipeline (paper: group pipelining): each env group exchanges its observations for an action
chunk, steps the chunk on its envs and emits finished trajectory segments, independently of the others.

Three parts, each over the bus API only (a Zenoh ``Bus`` or an in-memory one):

* :class:`ActionExchange` — observations out on ``obs/<group>``, the matching chunk in on ``act/<group>``;
  published again when no answer comes (a lost sample) or generation restarted (it has none in flight);
* :class:`SegmentOutbox` — segments out on ``traj/<group>``, held while no train is live (a restart, a
  new GPU share) up to ``train.max_pending`` decisions, and sent when one is back;
* :class:`GroupLoop` — one group's loop: GRPO gating, exchange, stepping, worker replacement (an env given up
  by the fleet takes no more chunks), segments; :class:`VectorGroupLoop` the same for a vectorized group (one
  batch of all its envs), in arrays, its segments packed (``traj/<group>/packed``). :func:`group_loop` picks.
"""

from __future__ import annotations

import asyncio
import collections
import logging
import time
from typing import Any, Callable

import numpy as np

from ebrl import obswire
from ebrl import graph
from ebrl.envs.obs import ObsLayout
from ebrl.envs.worker import VectorChunk, WorkerFailed
from ebrl.messages import ActionChunk, Observation, SegmentBatch, TrajectorySegment
from ebrl.meter import Telemetry
from ebrl.sched.fleet import EnvFleet, RolloutStats, VectorFleet
from ebrl.sched.modes import Schedule
from ebrl.sched.rollout import SegmentBuffers, SegmentBuilder

log = logging.getLogger(__name__)

# A group whose observation got no answer for this long publishes it again (a generation restart or a lost
# sample must never leave a group waiting forever).
ACTION_TIMEOUT_S = 30.0


class ActionExchange:
    """Observations for action chunks, per group; ``generation_restarted()`` makes every waiting group
    publish its observations again at once."""

    def __init__(self, bus: Any, run: str, groups: list[int], telemetry: Telemetry,
                 timeout_s: float = ACTION_TIMEOUT_S, action_shape: tuple[int, int] | None = None,
                 layout: ObsLayout | None = None, max_bytes: int | None = None):
        self.bus, self.run, self.telemetry, self.timeout_s = bus, run, telemetry, timeout_s
        self.keys = graph.keys_of(run, "sim")
        self.action_shape = action_shape  # (chunk, action dim): a chunk of another shape is dropped, counted
        self.layout = layout  # images of its uint8 fields travel as bytes (ebrl.obswire)
        # max_bytes: an action chunk's bound in this run (ebrl.sizes)
        self.actions = {g: bus.subscribe(self.keys.sub("act", group=g), ActionChunk, capacity=4, max_bytes=max_bytes)
                        for g in groups}
        self.gen_epoch = 0

    def generation_restarted(self) -> None:
        self.gen_epoch += 1

    async def exchange(self, g: int, seq: int, env_ids: np.ndarray, obs: np.ndarray) -> ActionChunk:
        """Publish group ``g``'s observations for chunk ``seq`` and wait for the chunk that answers them."""
        message = obswire.observation(self.layout, g, seq, env_ids, obs, time.time()) if self.layout is not None \
            else Observation(group=g, seq=seq, env_ids=env_ids, obs=obs, sent_at=time.time())
        while True:
            await self.bus.put(self.keys.put("obs", group=g), message, express=True)
            start, epoch = time.time(), self.gen_epoch
            deadline = time.monotonic() + self.timeout_s
            while time.monotonic() < deadline and epoch == self.gen_epoch:
                try:
                    _, chunk = await asyncio.wait_for(self.actions[g].next(), min(1.0, deadline - time.monotonic()))
                except asyncio.TimeoutError:
                    continue
                if self.action_shape is not None and chunk.actions.shape[1:] != self.action_shape:
                    self.bus.count_malformed(self.keys.sub("act", group=g), ValueError(
                        f"action chunk of shape {chunk.actions.shape[1:]}, expected {self.action_shape}"))
                    continue
                if chunk.seq == seq and chunk.actions.shape[0] == len(env_ids) == chunk.latents.shape[0]:
                    self.telemetry.publish_span(f"sim.g{g}", "wait", start, time.time(), busy=False)
                    return chunk
                self.telemetry.count("sim/stale_actions_dropped")
            self.telemetry.count("sim/obs_resent")
            if epoch == self.gen_epoch:
                log.warning("group %d: no actions for seq %d after %.0f s, publishing again", g, seq, self.timeout_s)


class SegmentOutbox:
    """Finished segments to train, or held while ``train_live()`` is False (at most ``max_pending``
    decisions; beyond that the oldest are dropped, counted): training resumes where it stopped."""

    def __init__(self, bus: Any, telemetry: Telemetry, max_pending: int, train_live: Callable[[], bool],
                 layout: ObsLayout | None = None):
        self.bus, self.telemetry, self.max_pending, self.train_live = bus, telemetry, max_pending, train_live
        self.layout = layout  # images of its uint8 fields travel (and wait here) as bytes (ebrl.obswire)
        self.held: collections.deque[tuple[str, TrajectorySegment | SegmentBatch]] = collections.deque()
        self.held_steps = 0

    async def send(self, key: str, segment: TrajectorySegment | SegmentBatch) -> None:
        if self.layout is not None:
            segment = obswire.segment(self.layout, segment)
        if self.train_live():
            await self.send_held()
            await self.bus.put(key, segment)
            return
        self.telemetry.count("sim/segments_while_train_down")
        self.held.append((key, segment))
        self.held_steps += len(segment.obs)
        while self.held_steps > self.max_pending:
            _, dropped = self.held.popleft()
            self.held_steps -= len(dropped.obs)
            self.telemetry.count("sim/segments_dropped_train_down")

    async def send_held(self) -> None:
        while self.held and self.train_live():
            key, segment = self.held.popleft()
            self.held_steps -= len(segment.obs)
            await self.bus.put(key, segment)
            self.telemetry.count("sim/segments_sent_late")


class GroupLoop:
    """One group, chunk after chunk: the envs that may act (GRPO waits for group-mates) get the chunk that
    answers their observations; their results become segments, cut at every iteration boundary
    (``schedule.length(sim_hosts())`` chunks) so that each update sees all of its iteration."""

    def __init__(self, g: int, fleet: EnvFleet, exchange: ActionExchange, outbox: SegmentOutbox,
                 stats: RolloutStats, telemetry: Telemetry, run: str, schedule: Schedule, segment_length: int,
                 sim_hosts: Callable[[], int]):
        self.g, self.fleet, self.exchange, self.outbox, self.stats = g, fleet, exchange, outbox, stats
        self.telemetry, self.run, self.schedule, self.sim_hosts = telemetry, run, schedule, sim_hosts
        self.keys = graph.keys_of(run, "sim")
        self.segment_length = segment_length
        self.env_ids = fleet.env_ids(g)
        self.builders = [SegmentBuilder(g, int(e), segment_length) for e in self.env_ids]
        self.seq = 0

    async def run_forever(self) -> None:
        obs = await self.fleet.reset_group(self.g)
        while not self.given_up():
            obs = await self.step(obs)
        log.error("group %d: every env given up; the group stops", self.g)
        if self.fleet.count() == 0:  # a sim service without envs fails: the launcher restarts it, or reports it
            raise RuntimeError("every env of this sim service was given up")

    def given_up(self) -> bool:
        return all(self.fleet.given_up_env(int(env)) for env in self.env_ids)

    async def step(self, obs: np.ndarray) -> np.ndarray:
        """One chunk of this group: returns the next observations."""
        g, episodes = self.g, self.fleet.episodes
        active = [i for i, env in enumerate(self.env_ids)
                  if not self.fleet.given_up_env(int(env)) and episodes.may_act(int(env))]
        if not active:  # every env waits for GRPO group-mates in other sim groups
            await episodes.moved()
            return obs
        chunk = await self.exchange.exchange(g, self.seq, self.env_ids, obs)
        self.fleet.saw_version(chunk.policy_version)
        start = time.time()
        done, latency_of = await self.fleet.run_chunk(g, active, chunk.actions[active])
        self.telemetry.publish_span(f"sim.g{g}", "chunk", start, time.time())
        boundary = (self.seq + 1) % self.schedule.length(self.sim_hosts()) == 0
        next_obs = obs.copy()
        for j, i in enumerate(active):
            next_obs[i] = await self.record(i, done[j], latency_of[j], obs[i], chunk, boundary)
        self.seq += 1
        return next_obs

    async def record(self, i: int, res: Any, latency: float, obs: np.ndarray, chunk: ActionChunk,
                     boundary: bool) -> np.ndarray:
        """What env ``i`` did with its chunk: a replaced worker (its episode so far is dropped, never
        published), or a decision added to its segment; returns its next observation."""
        env, episodes, count = int(self.env_ids[i]), self.fleet.episodes, self.telemetry.count
        if isinstance(res, WorkerFailed):
            log.warning("env %d: %s; replacing its worker (the episode in progress is dropped)", env, res)
            count("sim/worker_restarts")
            count("sim/partial_decisions_dropped", len(self.builders[i]))
            self.builders[i] = SegmentBuilder(self.g, env, self.segment_length)
            episode = episodes.index[env] + 1  # the episode numbering, hence GRPO's groups, carries on
            next_obs = await self.fleet.recover(self.g, i, episode)
            if next_obs is None:  # given up (the fleet logged why): it takes no more chunks
                self.telemetry.event("worker", f"env {env}: {res}; given up, its worker failed at every step")
                return obs
            self.telemetry.event("worker", f"env {env}: {res}; worker replaced")
            episodes.set(env, episode)
            return next_obs
        self.stats.chunk_latency.append(latency)
        self.stats.chunk_done(res)
        episodes.set(env, res.episode + int(res.terminated or res.truncated))
        count("sim/env_steps", res.steps)
        self.stats.env_steps += res.steps
        count("sim/step_busy_s", res.busy_s + res.helper_cpu_s)  # a multi-threaded simulator's threads too
        if res.guarded:  # what the env returned that training must not see as it was (ebrl.envs.guard)
            count("sim/rewards_clipped", res.guarded.rewards_clipped)
            count("sim/rewards_nonfinite", res.guarded.rewards_nonfinite)
            count("sim/obs_nonfinite", res.guarded.obs_nonfinite)
        if res.episode_return is not None:
            self.stats.episode_ended(env, res.episode, res.episode_return, res.episode_length or 0,
                                     res.episode_success, chunk.policy_version)
            count("sim/episodes")
        segment = self.builders[i].add(obs, chunk.actions[i], chunk.latents[i], float(chunk.logprobs[i]),
                                       float(chunk.values[i]), chunk.policy_version, res, boundary)
        if segment is not None:
            await self.outbox.send(self.keys.put("traj", group=self.g), segment)
            count("sim/segments")
        return res.next_obs


class VectorGroupLoop(GroupLoop):
    """A vectorized group's loop (:class:`~ebrl.sched.fleet.VectorFleet`: one batch of all its envs, every env
    acting every chunk): what :class:`GroupLoop` does env by env, in arrays over the batch. Its segments are cut
    where the per-env builders would cut them and go out packed, in :class:`~ebrl.messages.SegmentBatch` messages
    (:class:`~ebrl.sched.rollout.SegmentBuffers`)."""

    fleet: VectorFleet

    def __init__(self, g: int, fleet: VectorFleet, *args: Any, **kwargs: Any):
        super().__init__(g, fleet, *args, **kwargs)
        self.buffers = SegmentBuffers(g, self.env_ids, self.segment_length)

    def given_up(self) -> bool:
        return self.fleet.given_up_env(int(self.env_ids[0]))  # a vectorized group is given up as a whole

    async def step(self, obs: np.ndarray) -> np.ndarray:
        g = self.g
        chunk = await self.exchange.exchange(g, self.seq, self.env_ids, obs)
        self.fleet.saw_version(chunk.policy_version)
        start = time.time()
        result, latency = await self.fleet.run_vector_chunk(g, chunk.actions)
        self.telemetry.publish_span(f"sim.g{g}", "chunk", start, time.time())
        boundary = (self.seq + 1) % self.schedule.length(self.sim_hosts()) == 0
        self.seq += 1
        if isinstance(result, WorkerFailed):
            return await self.recover(obs, result)
        self.account(result, latency, chunk.policy_version)
        for segments in self.buffers.add(obs, chunk, result, boundary):
            await self.outbox.send(self.keys.put("packed", group=g), segments)
            self.telemetry.count("sim/segments", len(segments.env_ids))
        return result.next_obs  # type: ignore[return-value]  (VectorWorker.chunk filled it in)

    def account(self, result: VectorChunk, latency: float, version: int) -> None:
        """The chunk's counts, its latency, and each episode that ended in it."""
        count, stats, episodes = self.telemetry.count, self.stats, self.fleet.episodes
        stats.chunk_latency.append(latency)
        steps = int(result.steps.sum())
        count("sim/env_steps", steps)
        stats.env_steps += steps
        count("sim/step_busy_s", result.busy_s)
        for name, values in (("sim/rewards_clipped", result.rewards_clipped),
                             ("sim/rewards_nonfinite", result.rewards_nonfinite),
                             ("sim/obs_nonfinite", result.obs_nonfinite)):
            if values is not None and (total := int(values.sum())):
                count(name, total)
        for j, i in enumerate(result.ended.tolist()):
            env, episode, success = int(self.env_ids[i]), int(result.episode[i]), int(result.episode_success[j])
            episodes.set(env, episode + 1)
            stats.episode_ended(env, episode, float(result.episode_return[j]), int(result.episode_length[j]),
                                None if success < 0 else bool(success), version)
        if len(result.ended):
            count("sim/episodes", len(result.ended))

    async def recover(self, obs: np.ndarray, failed: WorkerFailed) -> np.ndarray:
        """The group's process failed: the segments in progress are dropped, every env starts its next episode
        on the new process (or the group is given up: the fleet logged why)."""
        log.warning("group %d: %s; replacing its process (the episodes in progress are dropped)", self.g, failed)
        self.telemetry.count("sim/worker_restarts")
        self.telemetry.count("sim/partial_decisions_dropped", self.buffers.drop())
        episodes, next_obs = self.fleet.episodes, obs.copy()
        for i, env in enumerate(self.env_ids.tolist()):
            episode = episodes.index[env] + 1  # the numbering carries on
            first = await self.fleet.recover(self.g, i, episode)
            if first is None:
                self.telemetry.event("worker", f"group {self.g}: {failed}; given up")
                return obs
            next_obs[i] = first
            episodes.set(env, episode)
        self.telemetry.event("worker", f"group {self.g}: {failed}; process replaced")
        return next_obs


def group_loop(g: int, fleet: EnvFleet, *args: Any, **kwargs: Any) -> GroupLoop:
    """Group ``g``'s loop: a :class:`VectorGroupLoop` for a vectorized fleet, else a :class:`GroupLoop`."""
    return (VectorGroupLoop if isinstance(fleet, VectorFleet) else GroupLoop)(g, fleet, *args, **kwargs)
