"""MuJoCo tasks written once for both engines: CPU MuJoCo (one environment, a gymnasium env) and MuJoCo Warp
(a batch of worlds stepped together on the GPU or the CPU, ebrl/envs/mjwarp.py).

A task is an MJCF model and four functions of the state of ``N`` worlds: what each episode starts from
(:meth:`MjTask.initial_state`, drawn on the host from the episode's own seed, so a world of a batch starts where
a worker process with the same seed would), what an action does (:meth:`MjTask.apply_action`, writing ``ctrl``
or ``mocap_pos``), what the policy sees (:meth:`MjTask.observe`) and what a step is worth
(:meth:`MjTask.evaluate`: reward, success, termination). The functions receive an :class:`MjState`, whose arrays
are ``[N, ...]`` views of the engine's own memory (numpy arrays over ``MjData`` with ``N = 1``, torch tensors over
MuJoCo Warp's device arrays), and ``xp``, the Python array API namespace of those arrays
(`array_api_compat <https://data-apis.org/array-api-compat/>`_: ``xp.linalg.vector_norm(x, axis=-1)``,
``xp.tanh``, ``xp.where``, ``xp.clip``, ``xp.concat``, ...). Code written against ``xp`` runs unchanged on both, so
the CPU version of a task and its GPU batch share one reward, one success check and one observation.

A user's own task is a subclass named in the config as ``env.id = "my_pkg.tasks:MyTask"`` (``env.backend =
"mjwarp"``), or run on CPU MuJoCo through :class:`MjTaskEnv` like any gymnasium env. Imports MuJoCo only (no torch,
no Warp): the CPU env workers load it.
"""

from __future__ import annotations

from dataclasses import dataclass, field
from typing import Any

import gymnasium as gym
import mujoco
import numpy as np

from ebrl.envs.obs import ObsLayout
from ebrl.envs.spec import EnvError
from ebrl.plugins import named_class


@dataclass
class MjInit:
    """One world's state at the start of an episode (host numpy arrays). ``mocap_pos``/``mocap_quat`` and
    ``ctrl``: None keeps the model's own (``body_pos``/``body_quat`` of the mocap bodies, zero controls)."""

    qpos: np.ndarray  # [nq]
    qvel: np.ndarray  # [nv]
    mocap_pos: np.ndarray | None = None  # [nmocap, 3]
    mocap_quat: np.ndarray | None = None  # [nmocap, 4]
    ctrl: np.ndarray | None = None  # [nu]
    task: dict[str, np.ndarray] = field(default_factory=dict)  # the task's own per-world variables


@dataclass
class MjState:
    """``N`` worlds' state as views of the engine's memory, each ``[N, ...]``: writes to ``ctrl``, ``mocap_pos``,
    ``mocap_quat`` and ``task`` are what the next step uses. Positions and frames (``xpos``, ``site_xpos``, ...)
    are those MuJoCo computed in the last step's forward pass (or after the reset)."""

    qpos: Any  # [N, nq]
    qvel: Any  # [N, nv]
    ctrl: Any  # [N, nu]
    mocap_pos: Any  # [N, nmocap, 3]
    mocap_quat: Any  # [N, nmocap, 4]
    xpos: Any  # [N, nbody, 3]
    xquat: Any  # [N, nbody, 4]
    site_xpos: Any  # [N, nsite, 3]
    site_xmat: Any  # [N, nsite, 3, 3]
    task: dict[str, Any]  # the task's per-world variables ([N, ...] each), declared by MjTask.task_fields


class MjTask:
    """A MuJoCo task for both engines (see the module's doc). Subclasses set the class attributes and define
    :meth:`mjcf`, :meth:`initial_state`, :meth:`apply_action`, :meth:`observe` and :meth:`evaluate`; keyword
    arguments from ``env.kwargs`` reach ``__init__`` (the batch's own keys, ebrl/envs/mjwarp.py, are taken
    out first)."""

    ctrl_dt: float = 0.02  # seconds of simulated time per env step: ctrl_dt / the model's timestep substeps
    max_episode_steps: int = 100  # the task's own time limit (env.max_episode_steps = 0 keeps it)
    action_size: int = 0
    obs_size: int = 0
    instruction: str = ""
    reward_range: tuple[float, float] | None = None  # one step's reward, where the task knows it (docs/security.md)

    def __init__(self, **kwargs: Any):
        if kwargs:
            raise EnvError(f"{type(self).__name__}: unknown env.kwargs {', '.join(map(repr, kwargs))}")
        self._model: mujoco.MjModel | None = None

    # --- what a task defines

    def mjcf(self) -> tuple[str, dict[str, bytes]]:
        """The model's MJCF text and the files it names (``{name: bytes}``; may be empty when the text names
        absolute paths)."""
        raise NotImplementedError

    def bind(self, model: mujoco.MjModel) -> None:
        """Look up what the functions below index (body, site and joint ids), once, after the model is built."""

    def task_fields(self) -> dict[str, tuple[int, ...]]:
        """The task's per-world variables and their shapes (float32), e.g. ``{"target": (3,)}``."""
        return {}

    def initial_state(self, rng: np.random.Generator) -> MjInit:
        raise NotImplementedError

    def apply_action(self, xp: Any, state: MjState, action: Any) -> None:
        """Write ``action`` ([N, action_size], already clipped to [-1, 1]) into ``state.ctrl`` or the mocaps."""
        raise NotImplementedError

    def observe(self, xp: Any, state: MjState) -> Any:
        """``[N, obs_size]`` float32."""
        raise NotImplementedError

    def evaluate(self, xp: Any, state: MjState) -> tuple[Any, Any, Any]:
        """After a step: reward ``[N]``, success ``[N]`` (bool), terminated ``[N]`` (bool)."""
        raise NotImplementedError

    # --- shared

    @property
    def model(self) -> mujoco.MjModel:
        """The compiled model (built and bound on first use)."""
        if self._model is None:
            text, assets = self.mjcf()
            self._model = mujoco.MjModel.from_xml_string(text, assets)
            self.bind(self._model)
        return self._model

    @property
    def substeps(self) -> int:
        steps = self.ctrl_dt / self.model.opt.timestep
        if steps < 1 or abs(steps - round(steps)) > 1e-6:
            raise EnvError(f"{type(self).__name__}: ctrl_dt = {self.ctrl_dt} is not a multiple of the model's "
                           f"timestep {self.model.opt.timestep}")
        return int(round(steps))

    def obs_layout(self) -> ObsLayout:
        return ObsLayout.vector(self.obs_size)


# --- the tasks EBRL ships, by name (a user's own: "pkg.module:ClassName")

TASKS = {"PandaPickCube-v0": "ebrl.envs.tasks.pick_cube:PandaPickCube"}


def task_class(name: str) -> type[MjTask]:
    """The :class:`MjTask` subclass ``name`` names: one of :data:`TASKS`, or ``"pkg.module:ClassName"``."""
    return named_class("env.id", name, TASKS, MjTask, EnvError)


def make_task(name: str, kwargs: dict[str, Any]) -> MjTask:
    try:
        return task_class(name)(**kwargs)
    except TypeError as exc:  # a keyword the task does not take
        raise EnvError(f"env.id = {name!r}: {exc}") from exc


def cpu_state(model: mujoco.MjModel, data: mujoco.MjData, task: dict[str, np.ndarray]) -> MjState:
    """One CPU MuJoCo world as an :class:`MjState` of ``N = 1`` numpy views."""
    return MjState(qpos=data.qpos[None], qvel=data.qvel[None], ctrl=data.ctrl[None],
                   mocap_pos=data.mocap_pos[None], mocap_quat=data.mocap_quat[None], xpos=data.xpos[None],
                   xquat=data.xquat[None], site_xpos=data.site_xpos[None],
                   site_xmat=data.site_xmat.reshape(1, model.nsite, 3, 3), task=task)


def load_init(model: mujoco.MjModel, data: mujoco.MjData, init: MjInit) -> None:
    """Start CPU MuJoCo's ``data`` from ``init`` (warm starts and time cleared, then a forward pass)."""
    mujoco.mj_resetData(model, data)
    data.qpos[:] = init.qpos
    data.qvel[:] = init.qvel
    if init.mocap_pos is not None:
        data.mocap_pos[:] = init.mocap_pos
    if init.mocap_quat is not None:
        data.mocap_quat[:] = init.mocap_quat
    if init.ctrl is not None:
        data.ctrl[:] = init.ctrl
    mujoco.mj_forward(model, data)


class MjTaskEnv(gym.Env):
    """One :class:`MjTask` world on CPU MuJoCo, as a gymnasium env (``info["success"]`` each step): the task on
    every machine, in EBRL's env worker processes, and in evaluation. ``render_mode="rgb_array"``: ``render()``
    draws the model's first camera (or the free camera) at ``render_size`` pixels."""

    metadata = {"render_modes": ["rgb_array"], "render_fps": 50}

    def __init__(self, task: MjTask, render_mode: str | None = None, render_size: int = 256):
        from array_api_compat import array_namespace

        self.task, self.render_mode, self.render_size = task, render_mode, int(render_size)
        self.model = task.model
        self.data = mujoco.MjData(self.model)
        self.substeps = task.substeps
        self.reward_range = task.reward_range
        self.metadata = {**self.metadata, "render_fps": int(round(1.0 / task.ctrl_dt))}
        self.vars = {name: np.zeros((1, *shape), np.float32) for name, shape in task.task_fields().items()}
        self.state = cpu_state(self.model, self.data, self.vars)
        self.xp = array_namespace(self.data.qpos)
        self.obs_layout = task.obs_layout()
        self.instruction = task.instruction
        self.observation_space = gym.spaces.Box(-np.inf, np.inf, (task.obs_size,), np.float32)
        self.action_space = gym.spaces.Box(-1.0, 1.0, (task.action_size,), np.float32)
        self._renderer: Any = None

    def reset(self, *, seed: int | None = None, options: dict | None = None):
        super().reset(seed=seed)
        init = self.task.initial_state(self.np_random)
        load_init(self.model, self.data, init)
        for name, value in self.vars.items():
            value[0] = init.task.get(name, 0.0)
        return self._obs(), {}

    def step(self, action):
        act = np.clip(np.asarray(action, np.float64).reshape(1, -1), -1.0, 1.0)
        self.task.apply_action(self.xp, self.state, act)
        for _ in range(self.substeps):
            mujoco.mj_step(self.model, self.data)
        reward, success, terminated = self.task.evaluate(self.xp, self.state)
        return (self._obs(), float(reward[0]), bool(terminated[0]), False, {"success": bool(success[0])})

    def _obs(self) -> np.ndarray:
        return np.asarray(self.task.observe(self.xp, self.state)[0], np.float32)

    def render(self) -> np.ndarray | None:
        if self.render_mode != "rgb_array":
            return None
        if self._renderer is None:  # the GL backend was chosen before mujoco was imported (render.with_rendering)
            self._renderer = mujoco.Renderer(self.model, self.render_size, self.render_size)
        self._renderer.update_scene(self.data, camera=0 if self.model.ncam else -1)
        return self._renderer.render()

    def close(self) -> None:
        if self._renderer is not None:
            self._renderer.close()
            self._renderer = None


def make_gym_env(task: str, render_mode: str | None = None, **kwargs: Any) -> MjTaskEnv:
    """gymnasium's entry point for a shipped task (``gym.make("ebrl.envs.tasks:PandaPickCube-v0")``)."""
    return MjTaskEnv(make_task(task, kwargs), render_mode=render_mode)
