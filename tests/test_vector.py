"""Vectorized groups (ebrl/envs/vector.py, VectorFleet): a group's envs stepped as one batch in one process.

The CPU batch (copies of a real MuJoCo env) must answer exactly what env worker processes answer for the same
seeds and actions; ManiSkill's GPU batch is driven through a fake with ManiSkill 3's batched API (no Vulkan GPU
here); a whole run goes through sim, gen and train with vectorized groups."""

from __future__ import annotations

import asyncio
import json
import os
import sys

import gymnasium as gym
import numpy as np
import pytest
import torch

from ebrl import config, devices
from ebrl.config import ConfigError
from ebrl.envs import EnvSpec, EnvWorker
from ebrl.envs import maniskill
from ebrl.envs.batch import BatchRunner, EnvBatch, ManiSkillBatch, make_batch
from ebrl.envs.vector import InlineVectorWorker, VectorWorker
from ebrl.envs.worker import WorkerFailed
from ebrl.sched.fleet import MAX_REPLACEMENTS, VectorFleet, make_fleet
from ebrl.sched.modes import Schedule, resolve
from helpers import ROOT
from test_env_hygiene import drive
from test_pipeline import run_services, segments_until_version, small_config

PENDULUM = EnvSpec("InvertedPendulum-v5", max_episode_steps=6)


def chunks_of_actions(n: int, k: int, count: int, seed: int = 0) -> list[np.ndarray]:
    rng = np.random.default_rng(seed)
    return [rng.uniform(-3.0, 3.0, (n, k, 1)).astype(np.float32) for _ in range(count)]


async def worker_answers(seeds: list[int], chunks: list[np.ndarray]):
    workers = [EnvWorker(PENDULUM, seed=s) for s in seeds]
    try:
        first = np.stack(await asyncio.gather(*(w.reset() for w in workers)))
        out = []
        for actions in chunks:
            out.append(await asyncio.gather(*(w.chunk(a) for w, a in zip(workers, actions))))
        return first, out
    finally:
        for w in workers:
            w.close()


def test_a_cpu_batch_answers_exactly_what_env_worker_processes_answer():
    """Same seeds, same actions: the same rewards, step counts, episode ends (inside chunks: the pendulum falls
    under strong actions; at the 6-step limit), observations, returns and episode indices."""
    seeds, k = [11, 12, 13], 4
    chunks = chunks_of_actions(len(seeds), k, 12)
    first, expected = asyncio.run(worker_answers(seeds, chunks))
    runner = BatchRunner(EnvBatch(PENDULUM, seeds))
    try:
        assert np.array_equal(runner.reset(np.zeros(3, np.int64)), first)
        ends_inside = 0
        for actions, want in zip(chunks, expected):
            got = runner.chunk(actions).results()
            for g, w in zip(got, want):
                assert (g.steps, g.terminated, g.truncated, g.episode) == (w.steps, w.terminated, w.truncated,
                                                                          w.episode)
                assert g.reward == pytest.approx(w.reward, rel=1e-6)
                assert np.allclose(g.final_obs, w.final_obs) and np.allclose(g.next_obs, w.next_obs)
                assert (g.episode_return is None) == (w.episode_return is None)
                if w.episode_return is not None:
                    assert g.episode_return == pytest.approx(w.episode_return, rel=1e-6)
                    assert g.episode_length == w.episode_length
                ends_inside += w.steps < k
        assert ends_inside > 0  # episodes did end inside chunks
    finally:
        runner.batch.close()


class Bomb(gym.Env):
    """Refuses any step after its episode's end (as robosuite does)."""

    observation_space = gym.spaces.Box(-1.0, 1.0, (2,), np.float32)
    action_space = gym.spaces.Box(-1.0, 1.0, (1,), np.float32)

    def __init__(self):
        self.t, self.done = 0, False

    def reset(self, *, seed=None, options=None):
        super().reset(seed=seed)
        self.t, self.done = 0, False
        return np.zeros(2, np.float32), {}

    def step(self, action):
        assert not self.done, "stepped after its episode ended"
        self.t += 1
        self.done = self.t >= 3
        return np.full(2, self.t / 10, np.float32), 1.0, False, self.done, {"success": self.t == 3}


gym.register("VectorBomb-v0", entry_point=Bomb)


def test_a_cpu_batch_never_steps_an_env_after_its_episode_ended_and_reports_success():
    runner = BatchRunner(EnvBatch(EnvSpec("VectorBomb-v0"), [0, 1]))
    runner.reset(np.zeros(2, np.int64))
    chunk = runner.chunk(np.zeros((2, 4, 1), np.float32))  # the episodes end at step 3 of 4
    assert chunk.steps.tolist() == [3, 3] and chunk.truncated.all() and chunk.reward.tolist() == [3.0, 3.0]
    assert chunk.ended.tolist() == [0, 1] and chunk.episode_success.tolist() == [1, 1]
    results = chunk.results()
    assert results[0].episode_return == 3.0 and results[0].episode_length == 3 and results[0].episode_success
    assert np.allclose(results[0].final_obs, 0.3) and np.allclose(results[0].next_obs, 0.0)  # reset after the end
    assert chunk.episode.tolist() == [0, 0] and runner.episodes.tolist() == [1, 1]


class FakeManiSkillBatch:
    """What ``gym.make("PickCube-v1", num_envs=N, sim_backend="physx_cuda", ...)`` returns, in ManiSkill 3's
    batched API: torch tensors [N, ...]; partial resets by ``options["env_idx"]`` returning every env's
    observation; ``terminated`` on success; the time limit as ``truncated``; every env steps at every call.
    Env i's state is a step counter; success when it reaches ``3 + i``."""

    made: dict = {}
    resets: list = []

    def __init__(self, **kwargs):
        FakeManiSkillBatch.made, FakeManiSkillBatch.resets = kwargs, []
        self.n = kwargs["num_envs"]
        self.limit = kwargs.get("max_episode_steps", 50)
        self.single_action_space = gym.spaces.Box(-1.0, 1.0, (8,), np.float32)
        self.t = torch.zeros(self.n)
        self.steps_taken = 0

    @property
    def unwrapped(self):
        return self

    def _obs(self):
        return self.t[:, None].repeat(1, 42)

    def reset(self, *, seed=None, options=None):
        idx = torch.arange(self.n) if not options else torch.as_tensor(options["env_idx"])
        FakeManiSkillBatch.resets.append((seed, idx.tolist()))
        self.t[idx] = 0.0
        return self._obs(), {"reconfigure": False}

    def step(self, action):
        assert isinstance(action, torch.Tensor) and action.shape == (self.n, 8)
        assert float(action.abs().max()) <= 1.0  # clipped to the action space
        self.steps_taken += 1
        self.t += 1
        success = self.t >= 3 + torch.arange(self.n)
        return (self._obs(), torch.full((self.n,), 0.5), success.clone(), self.t >= self.limit,
                {"success": success, "elapsed_steps": self.t.int()})

    def close(self):
        pass


@pytest.fixture
def fake_batch(monkeypatch):
    monkeypatch.setattr(maniskill, "_make_maniskill", lambda task, **kwargs: FakeManiSkillBatch(**kwargs))


def test_maniskill_batches_step_together_partially_reset_and_count_each_envs_own_steps(fake_batch):
    spec = EnvSpec("PickCube-v1", backend="maniskill", max_episode_steps=8, kwargs={"sim_backend": "physx_cuda"})
    batch = make_batch(spec, [5, 6, 7])
    assert isinstance(batch, ManiSkillBatch)
    made = FakeManiSkillBatch.made
    assert made["num_envs"] == 3 and made["sim_backend"] == "physx_cuda" and made["max_episode_steps"] == 8
    assert made["obs_mode"] == "state" and made["control_mode"] == "pd_joint_delta_pos"
    runner = BatchRunner(batch)
    assert runner.reset(np.zeros(3, np.int64)).shape == (3, 42)
    chunk = runner.chunk(np.full((3, 4, 8), 9.0, np.float32))  # env 0 succeeds at step 3, env 1 at step 4
    assert batch.env.steps_taken == 4  # the batch stepped 4 times: env 0's 4th step was dropped
    assert chunk.steps.tolist() == [3, 4, 4] and chunk.terminated.tolist() == [True, True, False]
    assert chunk.reward.tolist() == [1.5, 2.0, 2.0] and chunk.ended.tolist() == [0, 1]
    assert chunk.episode_success.tolist() == [1, 1] and chunk.episode_return.tolist() == [1.5, 2.0]
    assert chunk.final_obs[:, 0].tolist() == [3.0, 4.0]  # each env's observation at its own last step
    assert FakeManiSkillBatch.resets[-1] == (5 + 2 * 7919, [0, 1])  # one partial reset: the batch's 2nd
    assert chunk.next_obs[:, 0].tolist() == [0.0, 0.0, 4.0]
    results = chunk.results()
    assert results[2].episode_return is None and results[0].episode_success is True
    chunk = runner.chunk(np.zeros((3, 4, 8), np.float32))  # env 2 succeeds at its 5th step: the chunk's first
    assert chunk.steps.tolist() == [3, 4, 1] and chunk.episode.tolist() == [1, 1, 0]
    assert chunk.episode_length[chunk.ended.tolist().index(2)] == 5  # its episode ran over two chunks


def pendulum_answers() -> tuple[list[np.ndarray], np.ndarray, list]:
    """Six chunks of actions for two pendulums, and what a batch in this process answers: the first observations
    and each chunk's result (the pendulum falls inside the chunks, so final observations travel too)."""
    chunks = chunks_of_actions(2, 4, 6, seed=1)
    runner = BatchRunner(EnvBatch(PENDULUM, [1, 2]))
    first = runner.reset(np.zeros(2, np.int64))
    expected = [runner.chunk(actions) for actions in chunks]
    runner.batch.close()
    return chunks, first, expected


@pytest.mark.parametrize("obs_size", [0, 4], ids=["pipe", "shared_memory"])
def test_a_vectorized_group_process_answers_and_fails_like_a_worker(obs_size):
    """Observations through the pipe or through shared memory: the same answers (the pendulum falls inside the
    chunks, so final observations travel too)."""
    chunks, first, expected = pendulum_answers()

    async def scenario():
        worker = VectorWorker(PENDULUM, [1, 2], sorted(os.sched_getaffinity(0))[:1], obs_size)
        try:
            obs = await worker.reset(np.zeros(2, np.int64))
            assert obs.shape == (2, 4) and np.array_equal(obs, first)
            ended = 0
            for actions, want in zip(chunks, expected):
                got = await worker.chunk(actions, timeout=30)
                assert np.array_equal(got.next_obs, want.next_obs) and np.array_equal(got.final_obs, want.final_obs)
                assert got.steps.tolist() == want.steps.tolist()
                ended += len(got.ended)
            assert ended > 0 and worker.chunks_done == len(chunks)
            chunk = await worker.chunk(np.zeros((2, 3, 1), np.float32), timeout=30)
            assert chunk.steps.min() >= 1 and chunk.next_obs.shape == (2, 4)
            with pytest.raises(ValueError, match="a chunk for 3 envs"):  # a malformed request: said, not fatal
                await worker.chunk(np.zeros((3, 3, 1), np.float32), timeout=30)
            worker.proc.kill()
            with pytest.raises(WorkerFailed):
                await worker.chunk(np.zeros((2, 3, 1), np.float32), timeout=30)
        finally:
            worker.close()

    asyncio.run(scenario())


def test_a_vectorized_group_on_a_thread_of_the_sim_s_process_answers_and_fails_like_its_process():
    """InlineVectorWorker (the simulator sharing a process, run.processes): the same answers as the group's
    process, in this process's own thread (no child process); a malformed request is the batch's answer, a
    batch that raises is a failed group, and a failed group takes no more requests."""
    chunks, first, expected = pendulum_answers()

    async def scenario():
        import psutil

        children = set(p.pid for p in psutil.Process().children())
        worker = InlineVectorWorker(PENDULUM, [1, 2], sorted(os.sched_getaffinity(0))[:1])
        try:
            obs = await worker.reset(np.zeros(2, np.int64))
            assert np.array_equal(obs, first)
            assert set(p.pid for p in psutil.Process().children()) == children  # no process of its own
            for actions, want in zip(chunks, expected):
                got = await worker.chunk(actions, timeout=30)
                assert np.array_equal(got.next_obs, want.next_obs) and np.array_equal(got.final_obs, want.final_obs)
                assert got.steps.tolist() == want.steps.tolist() and got.busy_s >= 0
            assert worker.chunks_done == len(chunks) and worker.thread_id is not None
            assert os.sched_getaffinity(worker.thread_id) == set(sorted(os.sched_getaffinity(0))[:1])
            with pytest.raises(ValueError, match="a chunk for 3 envs"):  # a malformed request: said, not fatal
                await worker.chunk(np.zeros((3, 3, 1), np.float32), timeout=30)
            worker.runner.chunk = lambda actions: 1 / 0  # the batch itself fails: the group is lost
            with pytest.raises(WorkerFailed, match="ZeroDivisionError"):
                await worker.chunk(np.zeros((2, 3, 1), np.float32), timeout=30)
            with pytest.raises(WorkerFailed, match="is gone"):
                await worker.chunk(np.zeros((2, 3, 1), np.float32), timeout=30)
        finally:
            worker.close()

    asyncio.run(scenario())


def test_an_inline_vectorized_group_whose_env_fails_at_every_step_is_given_up_and_the_other_goes_on(caplog):
    fleet = vector_fleet("raise", bad_env=1, inline=True)
    try:
        assert all(isinstance(w, InlineVectorWorker) for w in fleet.vectors.values())
        answered = asyncio.run(drive(fleet, chunks=MAX_REPLACEMENTS + 4))
        assert answered == {0: 0, 1: 0, 2: MAX_REPLACEMENTS + 4, 3: MAX_REPLACEMENTS + 4}
        assert fleet.given_up_envs == {0, 1} and fleet.count() == 2
    finally:
        fleet.close()


def vector_fleet(fault: str, bad_env: int, inline: bool = False) -> VectorFleet:
    spec = EnvSpec("faulty_envs:Faulty-v0", kwargs={"fault": fault, "bad_env": bad_env})
    schedule = Schedule(mode="ebrl", groups=2, envs_per_group=2, stepping="batch", core_rebinding=False,
                        overlap=True, max_staleness=1, rollout_length=8, sim_cores=sorted(os.sched_getaffinity(0))[:1],
                        gen_cores=[], train_cores=[], vectorized=True)
    fleet = make_fleet(spec, schedule, host=0, seed=0, inline=inline)
    assert isinstance(fleet, VectorFleet)
    return fleet


def test_a_vectorized_group_whose_env_fails_at_every_step_is_given_up_and_the_other_group_goes_on(caplog):
    fleet = vector_fleet("raise", bad_env=1)  # env 1 is in group 0, with env 0
    try:
        answered = asyncio.run(drive(fleet, chunks=MAX_REPLACEMENTS + 4))
        assert answered == {0: 0, 1: 0, 2: MAX_REPLACEMENTS + 4, 3: MAX_REPLACEMENTS + 4}
        assert fleet.given_up_envs == {0, 1} and fleet.failures[0] == MAX_REPLACEMENTS + 1 and fleet.count() == 2
        assert asyncio.run(fleet.recover(0, 0, episode=99)) is None
        assert f"group 0 given up: its process failed {MAX_REPLACEMENTS + 1} times in a row" in caplog.text
    finally:
        fleet.close()


def test_a_killed_vectorized_group_process_is_replaced_with_each_envs_episode_numbering_carried_on():
    fleet = vector_fleet("", bad_env=-1)
    first = fleet.vectors[1]

    def kill_group_1(fleet: VectorFleet) -> None:  # once, after its second chunk
        if fleet.vectors[1] is first and first.chunks_done == 2:
            first.proc.kill()

    try:
        answered = asyncio.run(drive(fleet, chunks=6, between=kill_group_1))
        assert fleet.given_up == 0 and fleet.count() == 4 and fleet.failures[1] == 1
        assert answered == {0: 6, 1: 6, 2: 5, 3: 5}  # one chunk lost to the kill
        assert fleet.vectors[1] is not first and fleet.vectors[1].proc.is_alive()
        assert fleet.episodes.index[2] == fleet.episodes.index[3] == 1  # the episode in progress was dropped
    finally:
        fleet.close()


def test_vectorized_is_the_default_only_on_gpu_physics_and_refused_with_grpo(tmp_path):
    cfg = small_config(tmp_path)
    assert not config.vectorized(cfg) and not resolve(cfg).vectorized
    cfg = small_config(tmp_path, sim={"vectorized": True})
    schedule = resolve(cfg)
    assert schedule.vectorized and schedule.stepping == "batch" and not schedule.core_rebinding
    maniskill_toml = str(ROOT / "configs" / "maniskill.toml")
    gpu = config.load(maniskill_toml, ["env.kwargs.sim_backend=physx_cuda"])
    assert config.vectorized(gpu) and gpu.sim.vectorized == "auto"
    assert not config.vectorized(config.load(maniskill_toml, ["env.kwargs.sim_backend=physx_cpu"]))
    with pytest.raises(ConfigError, match="alloc.enabled: the allocator profiles"):
        config.load(maniskill_toml, ["env.kwargs.sim_backend=physx_cuda", "alloc.enabled=true"])
    with pytest.raises(ConfigError, match="sim.vectorized: grpo"):
        config.load(str(ROOT / "configs" / "grpo_pendulum.toml"), ["sim.vectorized=true"])


def test_a_vectorized_group_makes_its_backends_own_batch_else_copies_of_the_env():
    from ebrl.envs.batch import MjWarpBatch, maniskill_batch
    from ebrl.envs.records import backend_record

    assert backend_record("mjwarp").batch_maker({"device": "cpu"}) is MjWarpBatch
    assert backend_record("maniskill").batch_maker({"sim_backend": "physx_cuda"}) is maniskill_batch
    assert backend_record("maniskill").batch_maker({"sim_backend": "physx_cpu"}) is None
    assert backend_record("gymnasium").batch_maker({}) is None
    batch = make_batch(PENDULUM, [1, 2])
    try:
        assert isinstance(batch, EnvBatch) and len(batch.envs) == 2
    finally:
        batch.close()


def test_sim_gen_and_train_learn_with_vectorized_groups(tmp_path):
    """The whole loop over vectorized groups: segments from every env of both groups, versions advancing."""
    cfg = small_config(tmp_path, sim={"vectorized": True})
    seen: dict = {"segments": [], "versions": []}
    train, gen, sim = asyncio.run(run_services(cfg, tmp_path, segments_until_version(seen)))
    assert isinstance(sim.fleet, VectorFleet) and len(sim.fleet.vectors) == 2
    assert {s.env_id for s in seen["segments"]} == {0, 1, 2, 3} and train.learner.version >= 3
    assert max(int(s.versions.max()) for s in seen["segments"]) >= 1
    assert sim.meter.total("sim/env_steps") > 0 and sim.meter.total("sim/episodes") > 0


def test_the_maniskill_ppo_peer_runs_partial_resets_and_stops_at_the_target_success(tmp_path, monkeypatch):
    """benchmarks/peers/maniskill_ppo.py's loop on the fake batch (CPU tensors): episodes end by success, are
    reset in the same step, and 20 successes in a row end the run with the JSON written."""
    import importlib.util

    spec = importlib.util.spec_from_file_location("maniskill_ppo", ROOT / "benchmarks" / "peers" / "maniskill_ppo.py")
    peer = importlib.util.module_from_spec(spec)
    monkeypatch.setitem(sys.modules, "maniskill_ppo", peer)  # its dataclass looks itself up there
    spec.loader.exec_module(peer)
    monkeypatch.setattr(peer, "make_envs", lambda args: FakeManiSkillBatch(num_envs=args.num_envs,
                                                                           max_episode_steps=args.max_episode_steps))
    out = tmp_path / "peer.json"
    assert peer.main(["--num-envs", "4", "--num-steps", "8", "--num-minibatches", "2", "--hidden", "16,16",
                      "--total-timesteps", "3200", "--json", str(out)]) == 0
    result = json.loads(out.read_text())
    summary = result["summary"]
    assert summary["stop_reason"] == "target_success" and summary["target_reached"]["success_rate"] == 1.0
    assert summary["episodes"] >= 20 and summary["updates"] >= 1
    assert len(FakeManiSkillBatch.resets) > 1 and all(len(idx) < 4 for _, idx in FakeManiSkillBatch.resets[1:2])
    assert result["hyperparameters"]["gamma"] == 0.8 and result["hyperparameters"]["num_envs"] == 4


def test_maniskill_configs_put_physics_on_the_gpu_where_cuda_is(monkeypatch):
    for name, envs in (("maniskill.toml", 512), ("maniskill_rgb.toml", 256)):
        monkeypatch.setattr(devices, "cuda_available", lambda: True)
        cfg = config.load(str(ROOT / "configs" / name))
        assert cfg.env.kwargs["sim_backend"] == "auto" and cfg.num_envs == envs
        assert config.vectorized(cfg) and resolve(cfg).vectorized and cfg.run.target_success == 0.9
        assert devices.physx_backend("auto") == "physx_cuda"
        monkeypatch.setattr(devices, "cuda_available", lambda: False)  # no CUDA: CPU PhysX, a process per env
        assert not config.vectorized(cfg) and devices.physx_backend("auto") == "physx_cpu"
    assert devices.physx_backend(None) == "physx_cpu"


def _no_gpu_maniskill() -> str:
    if not torch.cuda.is_available():
        return "needs a CUDA device and ManiSkill (benchmarks/gpu/check.sh maniskill runs it on a GPU machine)"
    try:
        maniskill.preflight(EnvSpec("PickCube-v1", backend="maniskill", kwargs={"sim_backend": "physx_cuda"}))
    except Exception as exc:  # noqa: BLE001
        return str(exc)
    return ""


@pytest.mark.gpu
@pytest.mark.skipif(bool(_no_gpu_maniskill()), reason=_no_gpu_maniskill() or "-")
def test_a_real_pickcube_batch_steps_on_gpu_physx_with_partial_resets():
    spec = EnvSpec("PickCube-v1", backend="maniskill", max_episode_steps=6,
                   kwargs={"sim_backend": "physx_cuda", "control_mode": "pd_joint_delta_pos"})
    batch = make_batch(spec, list(range(16)))
    try:
        assert isinstance(batch, ManiSkillBatch) and batch.device.type == "cuda"
        runner = BatchRunner(batch)
        first = runner.reset(np.zeros(16, np.int64))
        assert first.shape == (16, 42) and np.isfinite(first).all()
        rng = np.random.default_rng(0)
        total_steps, ended = 0, 0
        for _ in range(4):  # 16 steps: every env's 6-step episode ends inside a chunk at least twice
            chunk = runner.chunk(rng.uniform(-1, 1, (16, 4, 8)).astype(np.float32))
            total_steps += int(chunk.steps.sum())
            ended += len(chunk.ended)
            assert np.isfinite(chunk.next_obs).all() and (chunk.steps >= 1).all()
        assert ended >= 32 and total_steps < 16 * 16  # steps after an episode's end were not counted
        assert (runner.episodes >= 2).all()
    finally:
        batch.close()


def test_a_gpu_sized_maniskill_config_on_cpu_physx_is_refused_before_anything_starts(monkeypatch):
    from ebrl.prepare import too_many_processes

    monkeypatch.setattr(devices, "cuda_available", lambda: False)  # "auto" falls back to CPU PhysX
    cfg = config.load(str(ROOT / "configs" / "maniskill.toml"))
    problem = too_many_processes(cfg, cores=2)
    assert problem.startswith("sim.envs_per_group = 256: 512 ManiSkill envs on CPU PhysX")
    assert "--set sim.envs_per_group=8" in problem
    assert too_many_processes(config.load(str(ROOT / "configs" / "maniskill.toml"), ["sim.envs_per_group=8"]), 2) \
        is None
    monkeypatch.setattr(devices, "cuda_available", lambda: True)  # GPU PhysX: one process per group
    assert too_many_processes(cfg, cores=2) is None
    assert too_many_processes(config.load(str(ROOT / "configs" / "quickstart.toml")), cores=2) is None
