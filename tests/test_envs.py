"""Env adapter and worker processes: ids in module:EnvId form, chunks, auto-reset, clear errors."""

import asyncio
import os
import pathlib
import subprocess
import sys
import typing

import numpy as np
import pytest

from ebrl.config import EnvSection
from ebrl.envs import EnvError, EnvSpec, EnvWorker, describe, make_env
from ebrl.envs.backends import BACKENDS


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


def test_every_configurable_backend_has_an_entry_and_unknown_ones_are_a_clear_error():
    assert set(BACKENDS) == set(typing.get_args(typing.get_type_hints(EnvSection)["backend"]))
    with pytest.raises(EnvError, match="env.backend = 'isaac'.*'gymnasium'"):
        make_env(EnvSpec("Lift", backend="isaac"))


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
