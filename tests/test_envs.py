"""Env adapter and worker processes: ids in module:EnvId form, chunks, auto-reset, clear errors."""

import asyncio
import dataclasses
import os
import pathlib
import subprocess
import sys
import typing

import numpy as np
import pytest

from ebrl import config
from ebrl.config import ConfigError, EnvSection
from ebrl.envs import EnvError, EnvSpec, EnvWorker, describe, make_env
from ebrl.envs.records import BACKENDS, backend_record


def test_importing_ebrl_envs_imports_no_simulator():
    """Each backend's module, and its simulator, is imported only when an environment of it is built."""
    code = ("import sys, ebrl.envs\n"
            "print(sorted(m for m in sys.modules if m.split('.')[0] in ('robosuite', 'mani_skill', 'sapien', "
            "'mujoco', 'torch') or m in ('ebrl.envs.gym', 'ebrl.envs.robosuite', 'ebrl.envs.maniskill')))")
    out = subprocess.run([sys.executable, "-c", code], capture_output=True, text=True, timeout=60, check=True,
                         cwd=pathlib.Path(__file__).resolve().parent.parent)
    assert out.stdout.strip() == "[]"


def test_the_sim_service_imports_no_torch():
    """torch costs a second or more at every sim start; only a vectorized group's own process needs it."""
    code = "import sys, ebrl.services.sim, ebrl.sched.fleet, ebrl.envs.vector\nprint('torch' in sys.modules)"
    out = subprocess.run([sys.executable, "-c", code], capture_output=True, text=True, timeout=60, check=True,
                         cwd=pathlib.Path(__file__).resolve().parent.parent)
    assert out.stdout.strip() == "False"


def test_the_configs_backends_are_the_registrys_and_unknown_ones_are_a_clear_error():
    assert typing.get_args(typing.get_type_hints(EnvSection)["backend"]) == tuple(BACKENDS)
    assert tuple(BACKENDS) == ("gymnasium", "robosuite", "maniskill", "mjwarp", "libero")
    with pytest.raises(EnvError, match="env.backend = 'isaac'.*'gymnasium'"):
        make_env(EnvSpec("Lift", backend="isaac"))
    with pytest.raises(ConfigError, match="env.backend = 'isaac': expected one of 'gymnasium', 'robosuite'"):
        config.from_dict({"env": {"backend": "isaac"}})
    described = {f.name: f.metadata["doc"] for f in dataclasses.fields(EnvSection)}
    assert "mjwarp: MuJoCo Warp, `pip install -e '.[mjwarp]'`" in described["backend"]
    assert "a ManiSkill task (PickCube-v1), an mjwarp task" in described["id"]
    assert " or a LIBERO suite (libero_spatial" in described["id"]
    assert "MuJoCo Warp: device, nconmax, njmax, cuda_graph" in described["kwargs"]


def test_each_backends_record_answers_what_its_name_was_tested_for(monkeypatch):
    """What the modules used to ask by testing a backend's name, each record answers (ebrl/envs/records.py)."""
    from ebrl import devices

    gym_, robosuite, maniskill, mjwarp, libero = (backend_record(name) for name in BACKENDS)
    monkeypatch.setattr(devices, "cuda_available", lambda: False)
    # sim.vectorized: always MuJoCo Warp's; "auto" ManiSkill's under GPU PhysX; otherwise only when asked
    assert mjwarp.vectorized(False, {}) and mjwarp.vectorized("auto", {"device": "cpu"})
    assert maniskill.vectorized("auto", {"sim_backend": "physx_cuda"}) and not maniskill.vectorized("auto", {})
    assert not maniskill.vectorized("auto", {"sim_backend": "auto"})  # no CUDA here: CPU PhysX
    assert not gym_.vectorized("auto", {}) and gym_.vectorized(True, {}) and not robosuite.vectorized(False, {})
    # physics on the GPU (a vectorized group's own batch: tests/test_vector.py)
    assert not mjwarp.gpu_physics({"device": "cpu"}) and mjwarp.gpu_physics({"device": "cuda:1"})
    assert not mjwarp.gpu_physics({}) and not gym_.gpu_physics({"device": "cuda"})
    monkeypatch.setattr(devices, "cuda_available", lambda: True)
    assert mjwarp.gpu_physics({}) and maniskill.vectorized("auto", {"sim_backend": "auto"})
    # cameras: robosuite's on asking, LIBERO's by default; both through MuJoCo's GL, ManiSkill's through SAPIEN
    assert not robosuite.cameras({}) and robosuite.cameras({"obs": "rgb"}) and robosuite.gl_cameras
    assert libero.cameras({}) and not libero.cameras({"obs": "state"}) and libero.gl_cameras
    assert maniskill.cameras({"obs": "rgb"}) and not maniskill.gl_cameras and not gym_.cameras({})
    assert [r.name for r in BACKENDS.values() if r.gl_frames] == ["gymnasium", "robosuite", "mjwarp", "libero"]
    # a GPU simulator whose tasks EBRL ships; what runs on the CPU instead; benchmark suites
    assert [r.name for r in BACKENDS.values() if r.gpu_simulator] == ["mjwarp"]
    assert mjwarp.ships("PandaPickCube-v0") and not mjwarp.ships("mytasks:Pick-v0") and not gym_.ships("Hopper-v5")
    assert [r.name for r in BACKENDS.values() if r.on_cpu] == ["maniskill"]
    assert "CPU PhysX (env.kwargs.sim_backend = 'auto'" in maniskill.on_cpu({"sim_backend": "auto"})
    assert [r.name for r in BACKENDS.values() if r.suites] == ["libero"]
    assert mjwarp.install in mjwarp.about.format(install=mjwarp.install) and not gym_.install


def test_module_colon_id_imports_the_users_module():
    info = describe(EnvSpec("user_envs:ShortPendulum-v0"))
    assert info.obs_shape == (4,) and info.action_dim == 1 and info.layout.describe() == "state:vector[4]"


def test_unknown_env_is_a_clear_error():
    with pytest.raises(EnvError, match="NoSuchEnv-v9"):
        make_env(EnvSpec("NoSuchEnv-v9"))
    with pytest.raises(EnvError, match="no_such_module"):
        make_env(EnvSpec("no_such_module:Env-v0"))


def test_worker_runs_chunks_and_resets_at_episode_end():
    async def scenario():
        worker = EnvWorker(EnvSpec("user_envs:ShortPendulum-v0"), seed=3)
        try:
            obs = await worker.reset()
            assert obs.shape == (4,) and obs.dtype == np.float32
            first = await worker.chunk(np.zeros((4, 1), np.float32))
            assert first.steps == 4 and first.reward == 4.0 and not (first.terminated or first.truncated)
            second = await worker.chunk(np.zeros((4, 1), np.float32))
            third = await worker.chunk(np.zeros((4, 1), np.float32))  # the 10-step limit falls inside it
            assert second.steps == 4 and third.steps == 2 and third.truncated
            assert third.episode_return == 10.0 and third.episode_length == 10
            assert not np.array_equal(third.final_obs, third.next_obs)  # next_obs is after the reset
        finally:
            worker.close()
        assert not worker.proc.is_alive()

    asyncio.run(scenario())


def test_a_worker_does_not_import_the_parents_main_module(tmp_path):
    """A forkserver child imports its parent's ``__main__`` first (for the sim service: ebrl.services.sim and all
    it imports); a worker needs none of it, and eight of them started in 3.8 s with it, 0.5 s without."""
    script = tmp_path / "parent.py"
    script.write_text(
        "import asyncio, os, sys\n"
        "if __name__ != '__main__':\n"
        "    open(os.environ['MARK'], 'a').write(__name__ + '\\n')\n"
        "else:\n"
        "    from ebrl.envs import EnvSpec, EnvWorker\n"
        "    async def main():\n"
        "        worker = EnvWorker(EnvSpec('user_envs:ShortPendulum-v0'), seed=0)\n"
        "        print((await worker.reset()).shape)\n"
        "        worker.close()\n"
        "    asyncio.run(main())\n")
    mark = tmp_path / "imported"
    root = pathlib.Path(__file__).resolve().parent
    out = subprocess.run([sys.executable, str(script)], capture_output=True, text=True, timeout=120,
                         env={**os.environ, "MARK": str(mark), "PYTHONPATH": f"{root.parent}:{root}"})
    assert out.returncode == 0 and out.stdout.strip() == "(4,)", out.stderr
    assert not mark.exists(), f"a worker imported the parent's main module as {mark.read_text()!r}"


def test_step_latency_spends_cpu_time():
    import time

    from ebrl.envs.latency import StepLatency

    env = StepLatency(make_env(EnvSpec("user_envs:ShortPendulum-v0")), mean_ms=3.0, sigma=0.0, seed=1)
    env.reset(seed=0)
    start = time.thread_time()
    for _ in range(5):
        env.step(np.zeros(1, np.float32))
    assert time.thread_time() - start >= 5 * 3e-3


def test_robosuite_lift_steps_resets_and_reports_success():
    env = make_env(EnvSpec("Lift", backend="robosuite", max_episode_steps=3))
    obs, _ = env.reset(seed=0)
    assert obs.shape == env.observation_space.shape and obs.dtype == np.float32
    assert env.action_space.shape == (7,)
    for t in range(3):
        obs, reward, terminated, truncated, info = env.step(env.action_space.sample())
        assert isinstance(info["success"], bool) and not terminated
    assert truncated  # the horizon ends the episode
    env.close()


def test_robosuite_unknown_task_is_a_clear_error():
    with pytest.raises(EnvError, match="NoSuchTask"):
        make_env(EnvSpec("NoSuchTask", backend="robosuite"))
