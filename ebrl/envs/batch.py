"""The batches a vectorized group's process steps (ebrl/envs/vector.py): ManiSkill's own batched environment, or
copies of any env in turn; and :class:`BatchRunner`, which runs chunks on either with each env's episode
bookkeeping. Imported in that process only (it needs torch; the sim service does not)."""

from __future__ import annotations

import time
from dataclasses import dataclass

import numpy as np
import torch

from ebrl.envs.backends import make_env
from ebrl.envs.spec import EnvError, EnvSpec
from ebrl.envs.vector import VectorChunk
from ebrl.envs.worker import EPISODE_SEED_STRIDE


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
        bases = [env.unwrapped for env in self.envs]
        # an env that can skip rendering the observations nobody reads (ebrl/envs/worker.py)
        self.lazy = [b if callable(getattr(b, "observe", None)) and hasattr(b, "skip_observation") else None
                     for b in bases]

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


def make_batch(spec: EnvSpec, seeds: list[int]) -> EnvBatch | ManiSkillBatch:
    """The batch a vectorized group runs: ManiSkill's own under GPU PhysX, else copies of the env in one process."""
    if spec.gpu_physics:
        return ManiSkillBatch(spec, len(seeds), seeds[0])
    return EnvBatch(spec, seeds)


class BatchRunner:
    """Chunks on a batch, with each env's episode bookkeeping (return, length, success, episode index)."""

    def __init__(self, batch: EnvBatch | ManiSkillBatch):
        self.batch = batch
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
        alive = torch.ones(n, dtype=torch.bool, device=device)
        reward = torch.zeros(n, dtype=torch.float64, device=device)
        steps = torch.zeros(n, dtype=torch.int64, device=device)
        terminated = torch.zeros(n, dtype=torch.bool, device=device)
        truncated = torch.zeros(n, dtype=torch.bool, device=device)
        success = torch.zeros(n, dtype=torch.bool, device=device)
        reports_success = False
        if self.obs is None:
            raise ValueError("a chunk before the first reset")
        final = self.obs
        step_s = []
        cpu0 = time.thread_time()
        for k in range(k_max):
            t0 = time.perf_counter()
            stepped = batch.step(acts[:, k], alive, observe=k == k_max - 1)
            step_s.append(time.perf_counter() - t0)
            reward += torch.where(alive, stepped.reward.double(), 0.0)
            steps += alive.long()
            if stepped.success is not None:
                reports_success = True
                success |= alive & stepped.success
            ended = alive & (stepped.terminated | stepped.truncated)
            terminated |= ended & stepped.terminated
            truncated |= ended & stepped.truncated
            final = torch.where(alive[:, None], stepped.obs, final)
            alive &= ~ended
            if k < k_max - 1 and not bool(alive.any()):  # every episode ended: the rest of the chunk is dropped
                break
        done = terminated | truncated
        self.ep_return += reward
        self.ep_length += steps
        self.ep_success |= success
        ended_idx = torch.nonzero(done).reshape(-1)
        ended = ended_idx.cpu().numpy()
        chunk_episode = self.episodes.copy()
        ep_return = self.ep_return[ended_idx].cpu().numpy()
        ep_length = self.ep_length[ended_idx].cpu().numpy()
        ep_success = (self.ep_success[ended_idx].to(torch.int8) if reports_success else
                      torch.full((len(ended),), -1, dtype=torch.int8)).cpu().numpy()
        final_obs = to_host(final[ended_idx], None if out is None else out[1, :len(ended)])
        if len(ended):
            self.episodes[ended] += 1
            self.ep_return[ended_idx] = 0.0
            self.ep_length[ended_idx] = 0
            self.ep_success[ended_idx] = False
            self.obs = batch.reset(ended, self.episodes[ended])
        else:
            self.obs = final
        busy = time.thread_time() - cpu0
        next_obs = to_host(self.obs, None if out is None else out[0])
        return VectorChunk(reward.cpu().numpy().astype(np.float32), steps.cpu().numpy(), terminated.cpu().numpy(),
                           truncated.cpu().numpy(), chunk_episode, next_obs, ended, final_obs,
                           ep_return, ep_length, ep_success, busy, tuple(step_s))


def to_host(values: torch.Tensor, out: np.ndarray | None) -> np.ndarray | None:
    """``values`` as a host array; or copied into ``out`` (shared memory), returning None."""
    if out is None:
        return values.cpu().numpy()
    torch.from_numpy(out).copy_(values.reshape(out.shape))
    return None
