"""The batches a vectorized group's process steps (ebrl/envs/vector.py): ManiSkill's own batched environment, a
MuJoCo Warp model of many worlds, or copies of any env in turn; and :class:`BatchRunner`, which runs chunks on any
of them with each env's episode bookkeeping. Imported in that process only (it needs torch; the sim service does not)."""

from __future__ import annotations

import logging
import math
import time
from dataclasses import dataclass
from typing import Any

import numpy as np
import torch
from gymnasium.utils import seeding

import ebrl.envs.guard as guard
from ebrl.envs.backends import lazy_observer, make_env
from ebrl.envs.mjtask import MjState, MjTask, make_task
from ebrl.envs.mjwarp import resolve_device, split_kwargs
from ebrl.envs.records import backend_record
from ebrl.envs.spec import EnvError, EnvSpec
from ebrl.envs.worker import EPISODE_SEED_STRIDE, VectorChunk

log = logging.getLogger(__name__)


@dataclass
class BatchStep:
    """What one step of a batch returns, on the batch's device."""

    obs: torch.Tensor  # [N, obs size] float32
    reward: torch.Tensor  # [N]
    terminated: torch.Tensor  # [N] bool
    truncated: torch.Tensor  # [N] bool
    success: torch.Tensor | None  # [N] bool, where the task reports success


class EnvBatch:
    """``n`` environments of any backend in this process, stepped one after another. Environment ``i`` starts
    episode ``k`` from ``reset(seed=seeds[i] + 7919 * k)``, as a worker process seeded ``seeds[i]`` does, so a
    vectorized group replays what the same envs in worker processes would."""

    device = torch.device("cpu")

    def __init__(self, spec: EnvSpec, seeds: list[int]):
        self.envs = []
        try:
            for seed in seeds:
                self.envs.append(make_env(spec, seed=seed))
        except BaseException:
            self.close()
            raise
        self.seeds = list(seeds)
        self.num_envs = len(self.envs)
        first = self.envs[0]
        self.low, self.high = first.action_space.low, first.action_space.high
        self.obs = np.zeros((self.num_envs, int(np.prod(first.observation_space.shape))), np.float32)
        # an env that can skip rendering the observations nobody reads (ebrl/envs/worker.py)
        self.lazy = [lazy_observer(env) if spec.lazy_render else None for env in self.envs]

    def reset(self, idx: np.ndarray, episodes: np.ndarray) -> torch.Tensor:
        """Start episode ``episodes[j]`` of env ``idx[j]``; every env's observation, [N, D]."""
        for i, episode in zip(idx, episodes):
            obs, _ = self.envs[i].reset(seed=self.seeds[i] + EPISODE_SEED_STRIDE * int(episode))
            self.obs[i] = np.asarray(obs, np.float32).reshape(-1)
        return torch.from_numpy(self.obs.copy())

    def step(self, actions: torch.Tensor, active: torch.Tensor, observe: bool = True) -> BatchStep:
        """Step the ``active`` envs (those whose episode has not ended in this chunk: an env may refuse steps
        after its episode's end, and they would be dropped anyway); the others keep their last observation.
        ``observe=False``: the observations after this step are not read (more steps of the chunk follow), so an
        env that can skip rendering does; one whose episode ends is always observed."""
        n = self.num_envs
        acts = np.clip(actions.numpy(), self.low, self.high)
        reward = np.zeros(n, np.float32)
        terminated, truncated = np.zeros(n, bool), np.zeros(n, bool)
        success = np.zeros(n, bool)
        reports = False
        for i in np.flatnonzero(active.numpy()):
            env, lazy = self.envs[i], self.lazy[i]
            if lazy is not None:
                lazy.skip_observation = not observe
            obs, r, te, tr, info = env.step(acts[i])
            if lazy is not None and lazy.skip_observation and (te or tr):
                obs = lazy.observe()
            self.obs[i] = np.asarray(obs, np.float32).reshape(-1)
            reward[i], terminated[i], truncated[i] = r, te, tr
            if "success" in info:
                reports, success[i] = True, bool(info["success"])
        return BatchStep(torch.from_numpy(self.obs.copy()), torch.from_numpy(reward), torch.from_numpy(terminated),
                         torch.from_numpy(truncated), torch.from_numpy(success) if reports else None)

    def close(self) -> None:
        for env in self.envs:
            env.close()


class ManiSkillBatch:
    """ManiSkill's batched environment of ``n`` envs (``num_envs = n``; on GPU PhysX under ``physx_cuda``).
    Partial resets are seeded ``seed + 7919 * k`` for the batch's k-th reset: a run is repeatable from its seed,
    though not env by env as with :class:`EnvBatch` (ManiSkill draws one episode seed per reset call)."""

    def __init__(self, spec: EnvSpec, n: int, seed: int):
        from ebrl.envs import maniskill as ms

        kwargs = dict(spec.kwargs)
        if "num_envs" in kwargs:
            raise EnvError("ManiSkill num_envs: set sim.envs_per_group instead (each group is one vectorized env)")
        obs = kwargs.pop("obs", "state")
        control_mode = kwargs.pop("control_mode", ms.DEFAULT_CONTROL_MODE)
        camera = kwargs.pop("camera", None)
        instruction = kwargs.pop("instruction", None)
        tokens = kwargs.pop("instruction_tokens", None)
        options = ms.make_options(n, spec.max_episode_steps or None, obs, kwargs.pop("sim_backend", None),
                                  kwargs.pop("image_size", ms.DEFAULT_IMAGE_SIZE), control_mode, kwargs)
        self.env = ms._make_maniskill(spec.id, **options)
        self.num_envs, self.seed, self.resets = n, seed, 0
        self.instruction = ms.INSTRUCTIONS.get(spec.id, "") if instruction is None else str(instruction)
        space = ms.action_box(spec.id, control_mode, self.env)
        raw, _ = self.env.reset(seed=seed)
        self.packer = ms.ObsPacker(obs, camera, self.instruction, obs == "rgb" if tokens is None else bool(tokens),
                                   raw)
        self.obs = self.packer.pack(raw)
        self.device = self.obs.device
        self.low = torch.as_tensor(space.low, device=self.device)
        self.high = torch.as_tensor(space.high, device=self.device)

    def reset(self, idx: np.ndarray, episodes: np.ndarray) -> torch.Tensor:
        self.resets += 1
        seed = self.seed + EPISODE_SEED_STRIDE * self.resets
        if len(idx) == self.num_envs:
            raw, _ = self.env.reset(seed=seed)
        else:
            raw, _ = self.env.reset(seed=seed, options={"env_idx": torch.as_tensor(idx, device=self.device)})
        self.obs = self.packer.pack(raw)
        return self.obs

    def step(self, actions: torch.Tensor, active: torch.Tensor, observe: bool = True) -> BatchStep:
        """Every env steps (GPU PhysX steps the whole batch); the caller drops what the inactive ones did."""
        raw, reward, terminated, truncated, info = self.env.step(torch.clamp(actions, self.low, self.high))
        success = info.get("success")
        as_bool = lambda value: torch.as_tensor(value, device=self.device).reshape(-1).bool()  # noqa: E731
        return BatchStep(self.packer.pack(raw), torch.as_tensor(reward, device=self.device).reshape(-1).float(),
                         as_bool(terminated), as_bool(truncated), None if success is None else as_bool(success))

    def close(self) -> None:
        self.env.close()


class MjWarpBatch:
    """``len(seeds)`` worlds of one :class:`~ebrl.envs.mjtask.MjTask` in one MuJoCo Warp model, on the GPU or the
    CPU (ebrl/envs/mjwarp.py says what it takes). World ``i`` starts episode ``k`` from the task's initial state for
    seed ``seeds[i] + 7919 k``, drawn on the host as a CPU env worker's; everything else stays on the device."""

    def __init__(self, spec: EnvSpec, seeds: list[int]):
        import mujoco_warp as mjw  # Warp: in this process only
        import warp as wp
        from array_api_compat import array_namespace

        own, task_kwargs = split_kwargs(dict(spec.kwargs))
        self.wp, self.mjw = wp, mjw
        self.task: MjTask = make_task(spec.id, task_kwargs)
        self.seeds = list(seeds)
        self.num_envs = n = len(seeds)
        self.limit = spec.max_episode_steps or self.task.max_episode_steps
        wp.config.log_level = wp.LOG_WARNING  # no init banner
        where = resolve_device(own["device"])
        self.wp_device = wp.get_device(where)
        self.device = torch.device(wp.device_to_torch(self.wp_device))
        self.nconmax, self.njmax = own["nconmax"], own["njmax"]
        mjm = self.task.model
        self.substeps = self.task.substeps
        with wp.ScopedDevice(self.wp_device):
            self.m = mjw.put_model(mjm)
            self.d = mjw.make_data(mjm, nworld=n, nconmax=self.nconmax, njmax=self.njmax)
        if self.device.type == "cuda":  # torch works on Warp's stream: one order for both, and graphs can capture
            torch.cuda.set_device(self.device)
            torch.cuda.set_stream(wp.stream_to_torch(self.wp_device))
        d, view = self.d, wp.to_torch
        self.vars = {name: torch.zeros((n, *shape), dtype=torch.float32, device=self.device)
                     for name, shape in self.task.task_fields().items()}
        self.state = MjState(qpos=view(d.qpos), qvel=view(d.qvel), ctrl=view(d.ctrl), mocap_pos=view(d.mocap_pos),
                             mocap_quat=view(d.mocap_quat), xpos=view(d.xpos), xquat=view(d.xquat),
                             site_xpos=view(d.site_xpos), site_xmat=view(d.site_xmat), task=self.vars)
        self.xp = array_namespace(self.state.qpos)
        self.elapsed = torch.zeros(n, dtype=torch.int64, device=self.device)
        self.nacon, self.nefc = view(d.nacon), view(d.nefc)
        self.unstable = 0  # worlds whose state went non-finite (their episode ended there, as a truncation)
        self.reset_mask = torch.zeros(n, dtype=torch.bool, device=self.device)  # the worlds the next reset clears
        reset_mask = wp.from_torch(self.reset_mask)
        # each a graph (Warp's own launches replayed without Python: a CUDA graph, or on the CPU Warp's replay),
        # or run eagerly; mjw.reset_data builds its kernels anew on each call, ~8 ms of hashing, a graph once
        self.graphed = bool(own["cuda_graph"])
        self.physics = self._graph(self._physics)
        self.clear = self._graph(lambda: mjw.reset_data(self.m, self.d, reset=reset_mask))
        self.forward = self._graph(lambda: mjw.forward(self.m, self.d))

    def _physics(self) -> None:
        for _ in range(self.substeps):
            self.mjw.step(self.m, self.d)

    def _graph(self, ops: Any) -> Any:
        """``ops`` (Warp launches only) as a callable that replays them: run once (it compiles their kernels; a
        first run is slow, Warp's kernel cache keeps them), then captured where ``env.kwargs.cuda_graph`` is true
        (on the CPU too: Warp >= 1.13 replays a CPU graph in C++). Eager, with one warning, where capture fails."""
        wp, where = self.wp, self.wp_device

        def eager() -> None:
            with wp.ScopedDevice(where):
                ops()

        eager()
        if not self.graphed:
            return eager
        try:
            with wp.ScopedDevice(where), wp.ScopedCapture(device=where) as capture:
                ops()
        except Exception as exc:  # noqa: BLE001 - an older Warp, a device without capture: the same ops, eagerly
            log.warning("MuJoCo Warp: no graph capture on %s (%s); its launches run one by one", where, exc)
            self.graphed = False
            return eager
        graph = capture.graph
        return lambda: wp.capture_launch(graph)

    def reset(self, idx: np.ndarray, episodes: np.ndarray) -> Any:
        """Start episode ``episodes[j]`` of world ``idx[j]`` (its initial state drawn on the host from the episode's
        seed, as a CPU worker's); every world's observation, [N, D] on the device."""
        state = self.state
        idx = np.asarray(idx, np.int64)
        if len(idx):
            inits = [self.task.initial_state(seeding.np_random(self.seeds[i] + EPISODE_SEED_STRIDE * int(k))[0])
                     for i, k in zip(idx, episodes)]
            rows = torch.as_tensor(idx, device=self.device)
            self.reset_mask.zero_()
            self.reset_mask[rows] = True
            self.clear()  # mjw.reset_data of the masked worlds

            def put(target: Any, values: list[Any]) -> None:
                target[rows] = torch.as_tensor(np.stack(values), dtype=target.dtype, device=self.device)

            put(state.qpos, [i.qpos for i in inits])
            put(state.qvel, [i.qvel for i in inits])
            for name in ("mocap_pos", "mocap_quat", "ctrl"):  # None: the model's own, as reset_data left them
                values = [getattr(i, name) for i in inits]
                if values[0] is not None:
                    put(getattr(state, name), values)
            for name, value in self.vars.items():
                put(value, [np.broadcast_to(np.asarray(i.task.get(name, 0.0), np.float32), value.shape[1:])
                            for i in inits])
            self.elapsed[rows] = 0
            # a whole forward pass, as CPU MuJoCo's reset: its accelerations warm-start the first step's solver
            self.forward()  # (kinematics alone parts them)
        return self.task.observe(self.xp, state)

    def step(self, actions: Any, active: Any, observe: bool = True) -> Any:
        """Every world steps (the inactive ones' results are dropped by the caller). A world whose state or reward
        is not finite (the physics diverged) ends its episode there as a truncation, reward 0."""
        self.task.apply_action(self.xp, self.state, torch.clamp(actions.to(self.device, torch.float32), -1.0, 1.0))
        self.physics()
        reward, success, terminated = self.task.evaluate(self.xp, self.state)
        obs = self.task.observe(self.xp, self.state)
        self.elapsed += 1
        reward = reward.to(torch.float32)
        active = active.to(self.device)
        bad = ~(torch.isfinite(obs).all(dim=1) & torch.isfinite(reward))
        # one transfer to the host per step: contacts, constraint rows, diverged worlds
        contacts, rows, diverged = torch.stack([self.nacon[0].long(), self.nefc.max().long(),
                                                  (bad & active).sum()]).tolist()
        if contacts >= self.nconmax * self.num_envs or rows >= self.njmax:  # a full buffer: Warp dropped the rest
            raise EnvError(f"MuJoCo Warp ran out of room ({contacts} contacts in {self.nconmax} x {self.num_envs} "
                           f"slots, {rows} constraint rows of {self.njmax} per world): raise env.kwargs.nconmax or "
                           "env.kwargs.njmax")
        if diverged:
            self._unstable(diverged)
            obs = torch.where(bad[:, None], torch.zeros_like(obs), obs)
            reward = torch.where(bad, torch.zeros_like(reward), reward)
        truncated = (self.elapsed >= self.limit) | bad
        return BatchStep(obs, reward, terminated & ~bad, truncated, success & ~bad)

    def _unstable(self, count: int) -> None:
        before, self.unstable = self.unstable, self.unstable + count
        if self.unstable.bit_length() > before.bit_length():  # said at 1, 2, 4, 8, ... in all
            log.warning("%d world(s) diverged (non-finite state); their episodes ended as truncations (%d so far)",
                        count, self.unstable)

    def close(self) -> None:
        self.physics = self.clear = self.forward = lambda: None  # the graphs go with their callables


def make_batch(spec: EnvSpec, seeds: list[int]) -> EnvBatch | ManiSkillBatch | MjWarpBatch:
    """The batch a vectorized group runs: its backend's own where the record names one (MuJoCo Warp's worlds,
    ManiSkill's under GPU PhysX: ``Backend.batch_maker``), else copies of the env in one process."""
    own = backend_record(spec.backend).batch_maker(spec.kwargs)
    return own(spec, seeds) if own is not None else EnvBatch(spec, seeds)


def maniskill_batch(spec: EnvSpec, seeds: list[int]) -> ManiSkillBatch:
    """ManiSkill's own batch of ``len(seeds)`` envs, seeded from the first (the maniskill record's batch maker)."""
    return ManiSkillBatch(spec, len(seeds), seeds[0])


@dataclass
class _ChunkSums:
    """What a chunk's steps added up to, per env ([N], on the batch's device), each env's up to its episode's end
    (:meth:`BatchRunner.chunk`)."""

    reward: torch.Tensor  # float64: the checked rewards' sum
    steps: torch.Tensor  # int64: the steps counted
    terminated: torch.Tensor  # bool
    truncated: torch.Tensor  # bool
    success: torch.Tensor  # bool: success seen (stays False where the task reports none)
    clipped: torch.Tensor  # int64: rewards clipped (ebrl.envs.guard)
    nonfinite: torch.Tensor  # int64: rewards not finite
    bad_obs: torch.Tensor  # int64: observations not finite
    reports_success: bool = False  # whether the task reports success at all

    @classmethod
    def zeros(cls, n: int, device: torch.device) -> _ChunkSums:
        """Nothing yet, for ``n`` envs."""

        def zeros(dtype: torch.dtype) -> torch.Tensor:
            return torch.zeros(n, dtype=dtype, device=device)

        return cls(reward=zeros(torch.float64), steps=zeros(torch.int64), terminated=zeros(torch.bool),
                   truncated=zeros(torch.bool), success=zeros(torch.bool), clipped=zeros(torch.int64),
                   nonfinite=zeros(torch.int64), bad_obs=zeros(torch.int64))


class BatchRunner:
    """Chunks on a batch, with each env's episode bookkeeping (return, length, success, episode index)."""

    def __init__(self, batch: EnvBatch | ManiSkillBatch | MjWarpBatch, max_abs_reward: float = math.inf):
        """``max_abs_reward``: each env step's reward is checked as a worker process checks it
        (:mod:`ebrl.envs.guard`: clipped to it, 0 where not finite; counted per env in the chunk)."""
        self.batch, self.bound = batch, max_abs_reward
        n, device = batch.num_envs, batch.device
        self.episodes = np.zeros(n, np.int64)
        self.ep_return = torch.zeros(n, dtype=torch.float64, device=device)
        self.ep_length = torch.zeros(n, dtype=torch.int64, device=device)
        self.ep_success = torch.zeros(n, dtype=torch.bool, device=device)
        self.obs: torch.Tensor | None = None

    def reset(self, episodes: np.ndarray, out: np.ndarray | None = None) -> np.ndarray | None:
        """Start episode ``episodes[i]`` on every env (a replaced worker carries each env's numbering on); the
        observations, or None when they were written into ``out`` ([2, N, D], :func:`to_host`)."""
        self.episodes = np.asarray(episodes, np.int64).copy()
        self.ep_return.zero_()
        self.ep_length.zero_()
        self.ep_success.zero_()
        self.obs = self.batch.reset(np.arange(self.batch.num_envs), self.episodes)
        return to_host(self.obs, None if out is None else out[0])

    def chunk(self, actions: np.ndarray, out: np.ndarray | None = None) -> VectorChunk:
        """Step ``actions`` ([N, K, A]) on the batch; each env's steps stop counting at its episode's end.
        ``out`` ([2, N, D], shared with the sim service): the next observations go to ``out[0]`` and the final ones
        of the envs whose episode ended to the first rows of ``out[1]``, instead of into the chunk (its
        ``next_obs`` and ``final_obs`` are then None)."""
        batch, device = self.batch, self.batch.device
        acts = torch.as_tensor(np.asarray(actions, np.float32), device=device)
        n, k_max = acts.shape[0], acts.shape[1]
        if n != batch.num_envs:
            raise ValueError(f"a chunk for {n} envs; this batch has {batch.num_envs}")
        sums = _ChunkSums.zeros(n, device)
        if self.obs is None:
            raise ValueError("a chunk before the first reset")
        cpu0 = time.thread_time()
        final, step_s = self._step(acts, k_max, sums)
        done = sums.terminated | sums.truncated
        self.ep_return += sums.reward
        self.ep_length += sums.steps
        self.ep_success |= sums.success
        ended_idx = torch.nonzero(done).reshape(-1)
        ended = ended_idx.cpu().numpy()
        chunk_episode = self.episodes.copy()
        ep_return = self.ep_return[ended_idx].cpu().numpy()
        ep_length = self.ep_length[ended_idx].cpu().numpy()
        ep_success = (self.ep_success[ended_idx].to(torch.int8) if sums.reports_success else
                      torch.full((len(ended),), -1, dtype=torch.int8)).cpu().numpy()
        final_obs = to_host(final[ended_idx], None if out is None else out[1, :len(ended)])
        self._next_episodes(ended_idx, ended, final)
        busy = time.thread_time() - cpu0
        next_obs = to_host(self.obs, None if out is None else out[0])
        return VectorChunk(sums.reward.cpu().numpy().astype(np.float32), sums.steps.cpu().numpy(),
                           sums.terminated.cpu().numpy(), sums.truncated.cpu().numpy(), chunk_episode, next_obs,
                           ended, final_obs, ep_return, ep_length, ep_success, busy, tuple(step_s),
                           sums.clipped.cpu().numpy(), sums.nonfinite.cpu().numpy(), sums.bad_obs.cpu().numpy())

    def _step(self, acts: torch.Tensor, k_max: int, sums: _ChunkSums) -> tuple[torch.Tensor, list[float]]:
        """Step the chunk's ``k_max`` actions per env (``acts``: [N, K, A] on the batch's device), adding what each
        env's steps did up to its episode's end into ``sums``; once every episode has ended the rest of the chunk is
        dropped. Returns each env's observation after its last counted step ([N, D]) and each batch step's wall
        seconds."""
        batch, bound = self.batch, self.bound
        reward, clipped, nonfinite, bad_obs = sums.reward, sums.clipped, sums.nonfinite, sums.bad_obs
        steps, terminated, truncated, success = sums.steps, sums.terminated, sums.truncated, sums.success
        alive = torch.ones_like(terminated)
        final = self.obs
        step_s = []
        for k in range(k_max):
            t0 = time.perf_counter()
            stepped = batch.step(acts[:, k], alive, observe=k == k_max - 1)
            step_s.append(time.perf_counter() - t0)
            step_reward, was_clipped, was_nonfinite = guard.rewards(stepped.reward.double(), bound)
            reward += torch.where(alive, step_reward, 0.0)
            clipped += alive & was_clipped
            nonfinite += alive & was_nonfinite
            steps += alive.long()
            if stepped.success is not None:
                sums.reports_success = True
                success |= alive & stepped.success
            step_obs, broken = guard.observations(stepped.obs)  # a non-finite state ends its episode, truncated
            bad_obs += alive & broken
            step_truncated = stepped.truncated | (broken & ~stepped.terminated)
            ended = alive & (stepped.terminated | step_truncated)
            terminated |= ended & stepped.terminated
            truncated |= ended & step_truncated
            final = torch.where(alive[:, None], step_obs, final)
            alive &= ~ended
            if k < k_max - 1 and not bool(alive.any()):  # every episode ended: the rest of the chunk is dropped
                break
        return final, step_s

    def _next_episodes(self, ended_idx: torch.Tensor, ended: np.ndarray, final: torch.Tensor) -> None:
        """Start the next episode of the envs in ``ended`` (``ended_idx``: the same on the batch's device), their
        bookkeeping from zero; ``self.obs`` is then every env's observation for the next chunk (``final``, each
        env's after the chunk, where no episode ended)."""
        if len(ended):
            self.episodes[ended] += 1
            self.ep_return[ended_idx] = 0.0
            self.ep_length[ended_idx] = 0
            self.ep_success[ended_idx] = False
            self.obs = self.batch.reset(ended, self.episodes[ended])
        else:
            self.obs = final


def to_host(values: torch.Tensor, out: np.ndarray | None) -> np.ndarray | None:
    """``values`` as a host array; or copied into ``out`` (shared memory), returning None."""
    if out is None:
        return values.cpu().numpy()
    torch.from_numpy(out).copy_(values.reshape(out.shape))
    return None
