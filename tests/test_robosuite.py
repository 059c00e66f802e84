"""robosuite tasks: state and camera observations, instructions, seeding, and the choice of offscreen GL backend.

Camera observations run in this process: choose_gl() decides the backend before the first render context is
built (robosuite builds it lazily, so it does not matter that other tests imported mujoco/robosuite first), and
the module fixture puts MUJOCO_GL and the cached choice back afterwards so that later tests see no change.
"""

import asyncio
import importlib
import os

import numpy as np
import pytest

from ebrl.envs import EnvSpec, EnvWorker, describe, make_env, tokenize
from ebrl.envs import render
from ebrl.envs import EnvError
from ebrl.envs.robosuite import INSTRUCTIONS

TASKS = ["Lift", "PickPlaceCan", "Stack"]
GL_VARS = ("MUJOCO_GL", "PYOPENGL_PLATFORM", render.CHOSEN_VAR)


def robosuite_env(task, steps=3, **kwargs):
    return make_env(EnvSpec(task, backend="robosuite", max_episode_steps=steps, kwargs=kwargs))


def parts(env, obs):
    return {name: part[0] for name, part in env.unwrapped.obs_layout.split(obs[None]).items()}


def red(image):  # robosuite's textured colours are muted: a margin over the other channels, not a level
    r, g, b = image
    return (r > g + 0.3) & (r > b + 0.3)


def green(image):
    r, g, b = image
    return (g > r + 0.15) & (g > b + 0.15)


@pytest.fixture(scope="module")
def gl():
    """The GL choice for this module's camera tests; the environment variables and cache restored after."""
    with pytest.MonkeyPatch.context() as mp:
        for var in GL_VARS:  # registers each for restoring, as it is now
            if var in os.environ:
                mp.setenv(var, os.environ[var])
            else:
                mp.delenv(var, raising=False)
        mp.setattr(render, "_chosen", render._chosen)
        yield render.choose_gl()


@pytest.fixture(scope="module")
def lift_rgb(gl):
    env = robosuite_env("Lift", obs="rgb", image_size=64)
    yield env
    env.close()


@pytest.mark.parametrize("task", TASKS)
def test_task_steps_and_reports_success_with_state_observations(task):
    env = robosuite_env(task)
    layout = env.unwrapped.obs_layout
    assert [f.name for f in layout.fields] == ["state"] and env.observation_space.shape == (layout.size,)
    assert env.unwrapped.instruction == INSTRUCTIONS[task]
    obs, _ = env.reset(seed=0)
    assert obs.shape == (layout.size,) and obs.dtype == np.float32
    for _ in range(3):
        obs, reward, terminated, truncated, info = env.step(env.action_space.sample())
        assert obs.shape == (layout.size,) and isinstance(info["success"], bool) and not terminated
    assert truncated
    env.close()


def test_describe_reports_layout_and_instruction_and_tokens_can_join_state():
    info = describe(EnvSpec("Lift", backend="robosuite", kwargs={"instruction": "raise the block",
                                                                 "instruction_tokens": True}))
    assert info.instruction == "raise the block"
    assert [(f.name, f.kind) for f in info.layout.fields] == [("state", "vector"), ("instruction", "tokens")]
    env = robosuite_env("Lift", instruction="raise the block", instruction_tokens=True)
    obs, _ = env.reset(seed=0)
    np.testing.assert_array_equal(parts(env, obs)["instruction"], tokenize("raise the block"))
    env.close()


def test_same_seed_same_initial_observation_other_seed_another():
    env = robosuite_env("Lift")
    first, _ = env.reset(seed=5)
    env.step(env.action_space.sample())
    again, _ = env.reset(seed=5)
    other, _ = env.reset(seed=6)
    np.testing.assert_array_equal(first, again)
    assert not np.array_equal(first, other)  # the cube is placed elsewhere
    env.close()


def test_invalid_options_are_clear_errors():
    with pytest.raises(EnvError, match="obs = 'depth'.*'state', 'rgb'"):
        robosuite_env("Lift", obs="depth")
    with pytest.raises(EnvError, match="image_size"):
        robosuite_env("Lift", obs="rgb", image_size=0)


def test_rgb_observation_is_an_upright_image_with_proprio_and_instruction(lift_rgb):
    env = lift_rgb
    assert env.unwrapped.obs_layout.describe() == "image:image[3, 64, 64] + proprio:vector[43] + instruction:tokens[16]"
    obs, _ = env.reset(seed=0)
    assert obs.shape == env.observation_space.shape and obs.dtype == np.float32
    p = parts(env, obs)
    image = p["image"]
    assert image.min() >= 0.0 and image.max() <= 1.0 and image.max() > 0.5
    # agentview looks at the robot across the table: the robot is at the top, the white table fills the bottom.
    # Upside down (MuJoCo's row order) the table would be at the top.
    assert image[:, :8].mean() < 0.7 and image[:, 32:].mean() > 0.9
    assert red(image).sum() >= 4  # "the red cube", in RGB channel order
    np.testing.assert_array_equal(p["instruction"], tokenize("lift the red cube"))
    # proprio is the robot's own state: the state observation's first part, without the object's pose
    state_env = robosuite_env("Lift")
    state, _ = state_env.reset(seed=0)
    state_env.close()
    np.testing.assert_allclose(p["proprio"], state[:43], atol=1e-6)
    obs, _, _, _, info = env.step(env.action_space.sample())
    assert isinstance(info["success"], bool) and obs.shape == env.observation_space.shape


def test_rgb_same_seed_same_image(lift_rgb):
    first, _ = lift_rgb.reset(seed=7)
    again, _ = lift_rgb.reset(seed=7)
    np.testing.assert_array_equal(first, again)


@pytest.mark.parametrize("task, colours", [("PickPlaceCan", ["red"]), ("Stack", ["red", "green"])])
def test_rgb_84_shows_the_objects_in_their_colours(gl, task, colours):  # the can is red; Stack's cubes red, green
    env = robosuite_env(task, obs="rgb", image_size=84)
    obs, _ = env.reset(seed=0)
    image = parts(env, obs)["image"]
    assert image.shape == (3, 84, 84)
    for colour in colours:
        assert {"red": red, "green": green}[colour](image).sum() >= 4, colour
    env.step(env.action_space.sample())
    env.close()


def test_rgb_env_runs_in_a_worker_process(gl):
    async def scenario():
        spec = EnvSpec("Lift", backend="robosuite", max_episode_steps=4, kwargs={"obs": "rgb", "image_size": 64})
        worker = EnvWorker(spec, seed=1)
        try:
            obs = await worker.reset()
            assert obs.shape == (3 * 64 * 64 + 43 + 16,)
            result = await worker.chunk(np.zeros((4, 7), np.float32))
            assert result.steps == 4 and result.truncated and result.episode_success is False
        finally:
            worker.close()

    asyncio.run(scenario())


def test_camera_renders_only_observations_that_are_read(gl):
    env = robosuite_env("Lift", steps=20, obs="rgb", image_size=64).unwrapped
    image = lambda obs: parts(env, obs)["image"]  # noqa: E731
    env.reset(seed=0)
    env.skip_observation = True  # a step inside a chunk: nobody reads its observation
    skipped, *_ = env.step(np.zeros(7))
    assert not image(skipped).any()
    seen = env.observe()  # the chunk's last state, rendered on demand
    env.skip_observation = False
    full, *_ = env.step(np.zeros(7))
    assert image(seen).mean() > 0.1 and np.abs(image(full) - image(seen)).mean() < 0.05

    async def scenario():  # through the worker: a chunk's observation and an episode's final one are real images
        spec = EnvSpec("Lift", backend="robosuite", max_episode_steps=6, kwargs={"obs": "rgb", "image_size": 64})
        worker = EnvWorker(spec, seed=1)
        try:
            await worker.reset()
            first = await worker.chunk(np.zeros((4, 7), np.float32))
            ended = await worker.chunk(np.zeros((4, 7), np.float32))  # the 6-step limit falls inside it
            assert first.steps == 4 and ended.steps == 2 and ended.truncated
            for obs in (first.next_obs, ended.final_obs, ended.next_obs):
                assert image(obs).mean() > 0.1
            inside = await worker.chunk(np.zeros((1, 7), np.float32), observe=False)  # a step inside a chunk
            assert not image(inside.next_obs).any()  # was not rendered
            last = await worker.chunk(np.zeros((1, 7), np.float32), observe=True)
            assert image(last.next_obs).mean() > 0.1
        finally:
            worker.close()

    asyncio.run(scenario())


def test_choose_gl_uses_an_explicit_mujoco_gl_untried(monkeypatch):
    for var in GL_VARS:
        monkeypatch.delenv(var, raising=False)
    monkeypatch.setattr(render, "_chosen", None)
    monkeypatch.setattr(render, "_probe", lambda backend: pytest.fail(f"tried {backend}"))
    monkeypatch.setenv("MUJOCO_GL", "osmesa")
    assert render.choose_gl() == "osmesa"
    assert os.environ[render.CHOSEN_VAR] == "osmesa" and os.environ["PYOPENGL_PLATFORM"] == "osmesa"


def test_choose_gl_says_what_failed_and_how_to_fix_it(monkeypatch):
    for var in GL_VARS:
        monkeypatch.delenv(var, raising=False)
    monkeypatch.setattr(render, "_chosen", None)
    with pytest.raises(render.RenderingUnavailable) as failed:
        render.choose_gl(["no-such-gl"])
    message = str(failed.value)
    assert "camera observations need" in message and "libosmesa6" in message and "set MUJOCO_GL" in message
    assert "MUJOCO_GL=no-such-gl: RuntimeError: invalid value for environment variable MUJOCO_GL" in message
    assert "MUJOCO_GL" not in os.environ and render._chosen is None  # nothing decided


def test_choose_gl_tells_robosuites_egl_from_an_explicit_one(monkeypatch):
    importlib.import_module("robosuite.utils.binding_utils")  # robosuite writes MUJOCO_GL=egl on import
    gl_context = render._mujoco_gl_context()  # where mujoco keeps the value it read on import
    assert hasattr(gl_context, "_MUJOCO_GL")

    for var in GL_VARS:
        monkeypatch.delenv(var, raising=False)
    monkeypatch.setattr(render, "_probe", lambda backend: None if backend == "osmesa" else "no")
    monkeypatch.setenv("MUJOCO_GL", "egl")
    monkeypatch.setattr(gl_context, "_MUJOCO_GL", "")  # mujoco saw no MUJOCO_GL: robosuite wrote it
    monkeypatch.setattr(render, "_chosen", None)
    assert render.choose_gl(["osmesa"]) == "osmesa"
    monkeypatch.setenv("MUJOCO_GL", "egl")
    monkeypatch.delenv(render.CHOSEN_VAR)
    monkeypatch.setattr(gl_context, "_MUJOCO_GL", "egl")  # mujoco saw it: somebody chose egl
    monkeypatch.setattr(render, "_chosen", None)
    assert render.choose_gl(["osmesa"]) == "egl"
