"""LIBERO adapter: the tasks of a LIBERO suite (robosuite 1.5 scenes, a Panda, language goals) as a gymnasium env.

``env.id`` is the suite (``libero_spatial``, ``libero_object``, ``libero_goal``, ``libero_10``, ``libero_90``);
``env.kwargs.tasks`` one task, a list, or (empty) the whole suite, spread over the envs: the env seeded ``s`` runs
task ``tasks[s % len(tasks)]`` (the fleet seeds env i with ``run.seed * 100003 + i``: consecutive envs, consecutive
tasks; a GRPO group's envs share a seed, so a task). Each episode starts from one of the task's 50 official
initial states, ``reset(seed)``'s ``seed % 50`` (or ``options={"init_state": j}``), then ``no_op_steps`` (10)
steps that leave the gripper open while the objects settle, as OpenVLA, LeRobot and RLinf evaluate; episodes last
the suite's step limit of LeRobot (280, 280, 300, 520, 400; ``env.max_episode_steps`` overrides) and end when the
task's own BDDL goal holds (reward 1, ``info["success"]``).

Observations (one flat float32 vector laid out by ``obs_layout``):

- ``obs = "rgb"``: per camera (``cameras``, default agent view and wrist) an ``image`` field (3, S, S), uint8 on
  the bus, turned 180 degrees from MuJoCo's buffer as OpenVLA and LeRobot feed policies; ``proprio`` = end
  effector position, its axis-angle orientation and the two gripper joints (8, the published policies' state);
  the ``instruction`` tokens;
- ``obs = "state"``: ``proprio``, ``objects`` (LIBERO's object states: each object's position, quaternion and
  pose relative to the gripper, zero-padded to ``object_state_size`` so that every task of a suite has one
  layout), and the ``instruction`` tokens.

Two costs of a plain wrapper are kept down: a reset does not rebuild the scene (``hard_reset=False``: ~0.02 s
instead of ~0.55 s; the initial state is set on the same model), and MuJoCo's arena, which robosuite's base
model sizes for 5000 contacts and constraint rows (~1.3 GB per env process), is ``arena_mb`` (64 MB by default).
Cameras render only the observation a chunk ends on (``skip_observation``/``observe()``, as for robosuite).
"""

from __future__ import annotations

import contextlib
import io
import os
from typing import Any

import gymnasium as gym
import numpy as np

from ebrl.envs import libero_suite as suite_mod
from ebrl.envs.obs import ObsField, ObsLayout, tokenize
from ebrl.envs.spec import EnvError, EnvSpec

os.environ.setdefault(suite_mod.CONFIG_VAR, str(suite_mod.config_dir()))  # before anything imports libero

OBS_MODES = ("rgb", "state")
CAMERAS = ("agentview", "robot0_eye_in_hand")
FIELD_NAMES = {"agentview": "agentview", "robot0_eye_in_hand": "wrist"}
DEFAULT_ARENA_MB = 64
OBJECT_STATE_SIZE = 128  # a multi-task state layout: LIBERO's scenes hold at most 8 objects of 14 values


class LiberoEnv(gym.Env):
    """One task of a LIBERO suite (the ``env_index``-th of ``tasks``, cyclically)."""

    metadata = {"render_modes": ["rgb_array"], "render_fps": 20}

    def __init__(self, suite: str = "libero_spatial", tasks: Any = None, *, env_index: int = 0, horizon: int = 0,
                 obs: str = "rgb", cameras: Any = CAMERAS, image_size: int = 128,
                 no_op_steps: int = suite_mod.NO_OP_STEPS,
                 init_states: bool = True, instruction_tokens: bool = True, object_state_size: int = 0,
                 arena_mb: int = DEFAULT_ARENA_MB, render_mode: str | None = None, render_size: int = 256,
                 **kwargs: Any):
        _check_options(obs, cameras, image_size, no_op_steps, arena_mb, render_mode)
        chosen = suite_mod.select(suite, tasks)
        self.task = chosen[int(env_index) % len(chosen)]
        self.suite, self.instruction = suite, self.task.language
        self.obs_mode, self.cameras = obs, tuple(cameras) if obs == "rgb" else ()
        self.horizon = int(horizon) or suite_mod.MAX_STEPS[suite]
        self.no_op_steps, self.render_mode, self.render_size = int(no_op_steps), render_mode, int(render_size)
        self._init_states = suite_mod.init_states(self.task) if init_states else None
        self.env = _make(self.task, self.cameras, image_size, render_mode is not None, arena_mb, kwargs)
        _release_build_memory()
        self._upside_down = _opengl_images()
        self._tokens = tokenize(self.instruction)
        self.action_space = gym.spaces.Box(-1.0, 1.0, (int(self.env.action_dim),), dtype=np.float32)
        for camera in self.cameras:  # they render on demand (observe), never inside env.step
            self.env.modify_observable(f"{camera}_image", "enabled", False)
        raw = self.env._get_observations(force_update=True)
        objects = int(np.size(raw.get("object-state", ())))
        pad = int(object_state_size) or (objects if len(chosen) == 1 else OBJECT_STATE_SIZE)
        if obs == "state" and objects > pad:
            raise ValueError(f"LIBERO object_state_size = {pad}: {self.task.name} has {objects} object-state values")
        self.obs_layout = self._layout(image_size, pad, instruction_tokens)
        self.observation_space = gym.spaces.Box(-np.inf, np.inf, (self.obs_layout.size,), dtype=np.float32)
        self.t, self.init_state = 0, -1
        self.skip_observation = False  # set by the env worker on steps whose observation nobody reads
        if obs == "rgb":  # the object states are privileged: a camera policy does not read them, nor computes them
            for name in [n for n, o in self.env._observables.items() if o.modality == "object" and n in raw]:
                self.env.modify_observable(name, "enabled", False)

    def _layout(self, image_size: int, objects: int, with_tokens: bool) -> ObsLayout:
        fields = [ObsField(FIELD_NAMES.get(c, c), "image", (3, image_size, image_size), uint8=True)
                  for c in self.cameras]
        fields.append(ObsField("proprio", "vector", (8,)))
        if self.obs_mode == "state":
            fields.append(ObsField("objects", "vector", (objects,)))
        if with_tokens:
            fields.append(ObsField("instruction", "tokens", self._tokens.shape))
        return ObsLayout(tuple(fields))

    def _obs(self, raw: dict[str, np.ndarray]) -> np.ndarray:
        from robosuite.utils.transform_utils import quat2axisangle

        parts: dict[str, Any] = {"proprio": np.concatenate([raw["robot0_eef_pos"], quat2axisangle(
            raw["robot0_eef_quat"]), raw["robot0_gripper_qpos"]]), "instruction": self._tokens}
        for camera, field in zip(self.cameras, self.obs_layout.fields):
            image = raw.get(f"{camera}_image")  # (H, W, 3) uint8; absent while the cameras are off
            if image is None:
                parts[field.name] = np.zeros(field.shape, np.float32)
            else:  # MuJoCo's buffer turned 180 degrees, as published LIBERO policies see it
                image = image[::-1, ::-1] if self._upside_down else image[:, ::-1]
                parts[field.name] = image.transpose(2, 0, 1) / np.float32(255)
        if self.obs_mode == "state":
            objects = np.ravel(raw.get("object-state", ()))
            size = self.obs_layout.fields[1].size
            parts["objects"] = np.pad(objects, (0, size - objects.size))
        return self.obs_layout.pack(parts)

    def reset(self, *, seed: int | None = None, options: dict | None = None):
        """From the official initial state ``options["init_state"]``, else ``seed % 50`` (the next one without a
        seed); with ``init_states=false`` from LIBERO's own random placement (seeded by ``seed``)."""
        super().reset(seed=seed)
        if seed is not None:
            np.random.seed(seed % 2**32)  # LIBERO's placement samplers draw from numpy's global generator
        self._soft_reset()
        if self._init_states is not None:
            count = len(self._init_states)
            index = (options or {}).get("init_state", seed if seed is not None else self.init_state + 1)
            self.init_state = int(index) % count
            self.env.sim.set_state_from_flattened(self._init_states[self.init_state])
            self.env.sim.forward()
            self.env._post_process()
            self.env._update_observables(force=True)
        for _ in range(self.no_op_steps):
            self.env.step(np.asarray(suite_mod.NO_OP_ACTION, np.float64))
        self.t = 0
        info = {"task": self.task.name, "task_index": self.task.index, "init_state": self.init_state}
        return self.observe(), info

    def _soft_reset(self) -> None:
        from robosuite.utils.errors import RandomizationError

        for attempt in range(100):  # LIBERO's placement sampler gives up on some draws; it retries (env_wrapper.py)
            try:
                self.env.reset()
                return
            except RandomizationError:
                if attempt == 99:
                    raise

    def step(self, action):
        raw, reward, done, info = self.env.step(np.asarray(action, dtype=np.float64))
        self.t += 1
        success = bool(done)  # LIBERO's step returns its task's goal check (_check_success) as done
        info = dict(info, success=success)
        obs = self.observe() if self.cameras and not self.skip_observation else self._obs(raw)
        return obs, float(reward), success, self.t >= self.horizon, info

    def observe(self) -> np.ndarray:
        """The full observation of the current state; with cameras, renders them now."""
        if not self.cameras:
            return self._obs(self.env._get_observations())
        names = [f"{c}_image" for c in self.cameras]
        for name in names:
            self.env.modify_observable(name, "enabled", True)
        try:
            return self._obs(self.env._get_observations(force_update=True))
        finally:
            for name in names:
                self.env.modify_observable(name, "enabled", False)

    def render(self) -> np.ndarray | None:
        """With ``render_mode="rgb_array"``: the agent view, ``render_size`` square, (H, W, 3) uint8."""
        if self.render_mode != "rgb_array":
            return None
        frame = self.env.sim.render(camera_name="agentview", width=self.render_size, height=self.render_size)
        return np.ascontiguousarray(frame[::-1, ::-1] if self._upside_down else frame[:, ::-1])

    def close(self) -> None:
        self.env.close()
        _release_build_memory()  # the model's memory back to the system: describe() builds and closes one env


def _check_options(obs: str, cameras: Any, image_size: Any, no_op_steps: Any, arena_mb: Any,
                   render_mode: Any) -> None:
    if obs not in OBS_MODES:
        raise ValueError(f"LIBERO obs = {obs!r}: expected one of {', '.join(map(repr, OBS_MODES))}")
    if obs == "rgb" and (isinstance(cameras, str) or not cameras or not all(isinstance(c, str) for c in cameras)):
        raise ValueError(f"LIBERO cameras = {cameras!r}: expected a non-empty list of camera names, e.g. "
                         f"{list(CAMERAS)}")
    for name, value, low in (("image_size", image_size, 1), ("no_op_steps", no_op_steps, 0), ("arena_mb", arena_mb, 1)):
        if isinstance(value, bool) or not isinstance(value, int) or value < low:
            raise ValueError(f"LIBERO {name} = {value!r}: expected an integer >= {low}")
    if render_mode not in (None, "rgb_array"):
        raise ValueError(f"LIBERO render_mode = {render_mode!r}: only \"rgb_array\" is supported")


def _opengl_images() -> bool:
    from robosuite import macros

    return macros.IMAGE_CONVENTION == "opengl"  # MuJoCo renders bottom row first


def _import_libero() -> Any:
    """``libero.libero.envs`` (LIBERO's problem classes), quietly; robosuite 1.5's fix-ups applied."""
    from ebrl.envs.robosuite import _import_robosuite

    _import_robosuite()  # quiet, and MUJOCO_GL left as it was
    try:
        with contextlib.redirect_stderr(io.StringIO()):  # gym 0.26 (LIBERO's vector envs) prints a notice
            import gym  # noqa: F401
        from libero.libero import envs
        from libero.libero.envs.robots.on_the_ground_panda import OnTheGroundPanda
    except ImportError as exc:
        raise suite_mod.LiberoMissing(f"env.backend = 'libero' needs LIBERO ({exc}): {suite_mod.INSTALL_HINT}") \
            from exc
    # robosuite 1.5 mounts a robot on its default_base: LIBERO-Object's floor Panda has none ("NullMount")
    OnTheGroundPanda.default_base = property(lambda self: "NullMount")
    return envs


_sized_classes: dict[tuple[type, int], type] = {}


def _sized(cls: type, arena_mb: int) -> type:
    """``cls`` whose MuJoCo model sizes its arena (contacts, constraints, the solver's stack) to ``arena_mb``
    instead of what robosuite's base model's ``nconmax``/``njmax`` = 5000 make it (~1.3 GB)."""
    if (cls, arena_mb) not in _sized_classes:
        def _load_model(self: Any) -> None:
            cls._load_model(self)
            for size in self.model.root.iter("size"):
                size.attrib.pop("nconmax", None)
                size.attrib.pop("njmax", None)
                size.set("memory", f"{arena_mb}M")

        _sized_classes[cls, arena_mb] = type(cls.__name__, (cls,), {"_load_model": _load_model,
                                                                   "__module__": cls.__module__})
    return _sized_classes[cls, arena_mb]


def _make(task: suite_mod.Task, cameras: tuple[str, ...], image_size: int, renders: bool, arena_mb: int,
          kwargs: dict[str, Any]) -> Any:
    """The task's LIBERO problem env (as LIBERO's ControlEnv makes it: OSC_POSE arm, 20 Hz), never resetting by
    rebuilding, with an offscreen renderer only where something renders; ``kwargs`` override any option."""
    if cameras or renders:
        from ebrl.envs.render import choose_gl

        choose_gl()  # before robosuite imports mujoco, whose GL backend is fixed on import
    envs = _import_libero()
    import robosuite
    from libero.libero.envs import bddl_utils

    from ebrl.envs.robosuite import _use_gl

    if cameras or renders:
        _use_gl(os.environ["MUJOCO_GL"])
    controller = robosuite.load_composite_controller_config(controller=None, robot="Panda")
    for part in controller.get("body_parts", {}).values():
        part["type"] = "OSC_POSE"
    problem = bddl_utils.get_problem_info(str(task.bddl_file))["problem_name"]
    options = dict(robots=["Panda"], controller_configs=controller, use_camera_obs=bool(cameras),
                   has_renderer=False, has_offscreen_renderer=bool(cameras) or renders, control_freq=20,
                   horizon=10**9, ignore_done=True, hard_reset=False, camera_names=list(cameras),
                   camera_heights=image_size, camera_widths=image_size, camera_depths=False)
    options.update(kwargs)
    return _sized(envs.TASK_MAPPING[problem], arena_mb)(str(task.bddl_file), **options)


def _release_build_memory() -> None:
    """What building the scene leaves behind and a reset without a rebuild never uses: MuJoCo's asset cache
    (decoded textures and meshes, ~230 MB for a LIBERO scene) and the heap the compiler freed (~100 MB)."""
    import ctypes

    import mujoco

    mujoco.mj_clearCache(mujoco.mj_getCache())
    try:
        ctypes.CDLL("libc.so.6").malloc_trim(0)  # glibc: give freed heap pages back to the system
    except (OSError, AttributeError):
        pass


def build(spec: EnvSpec, seed: int = 0) -> LiberoEnv:
    """The backend's builder (ebrl/envs/backends.py): ``seed`` (the worker's) picks the task; episodes end at
    ``max_episode_steps``, else the suite's limit."""
    return LiberoEnv(spec.id, env_index=seed, horizon=spec.max_episode_steps, **spec.kwargs)


def preflight(spec: EnvSpec) -> None:
    """Before any process starts: the suite and tasks exist, LIBERO and its assets are set up."""
    try:
        suite_mod.select(spec.id, spec.kwargs.get("tasks"))
        suite_mod.check()
    except (ValueError, suite_mod.LiberoMissing) as exc:
        raise EnvError(f"env.id = {spec.id!r} (backend libero): {exc}") from None
