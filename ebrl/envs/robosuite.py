"""robosuite adapter: a manipulation task (Lift, PickPlaceCan, Stack, ...) as a gymnasium environment.

Two observation modes, each one flat float32 vector laid out by ``obs_layout``:

- ``obs = "state"``: ``state`` = ``robot0_proprio-state`` followed by ``object-state``
  (privileged object poses), plus the ``instruction`` tokens if asked for;
- ``obs = "rgb"``: ``image`` (3, H, W) from one camera in [0, 1], right side up,
  ``proprio`` = ``robot0_proprio-state`` (no object state: the camera has to see it),
  and the ``instruction`` tokens.

The episode is truncated at the horizon (robosuite tasks do not terminate), and
``info["success"]`` is the task's own success check.

Rendering is most of the cost of a camera step, and inside an action chunk only
the last step's observation is read. So robosuite's camera observable stays
disabled while the simulation steps, and the camera renders the state after a
step only when its observation is wanted: the env honours ``skip_observation``
(the image part is then zeros) and ``observe()`` renders the current state on
demand. The env worker sets it for every step of a chunk but the last, and
calls ``observe()`` when an episode ends mid-chunk (ebrl/envs/worker.py).
"""

from __future__ import annotations

import logging
import os
from typing import Any

import gymnasium as gym
import numpy as np

from ebrl.envs.obs import ObsField, ObsLayout, tokenize
from ebrl.envs.spec import EnvSpec

DEFAULT_HORIZON = 200
OBS_MODES = ("state", "rgb")
PROPRIO_KEY = "robot0_proprio-state"
OBJECT_KEY = "object-state"
# what each task asks for, with the objects' colours as robosuite 1.5.1 builds them (lift.py, stack.py, pick_place.py)
INSTRUCTIONS = {
    "Lift": "lift the red cube",
    "PickPlaceCan": "pick up the can and place it in its bin",
    "Stack": "stack the red cube on the green cube",
}


class RobosuiteEnv(gym.Env):
    """One robosuite task with a Panda arm. ``kwargs`` not named here go to ``robosuite.make``."""

    metadata = {"render_modes": ["rgb_array"]}

    def __init__(self, task: str, horizon: int = DEFAULT_HORIZON, *, obs: str = "state", camera: str = "agentview",
                 image_size: int = 64, instruction: str | None = None, instruction_tokens: bool | None = None,
                 render_mode: str | None = None, render_size: int = 256, **kwargs: Any):
        """``render_mode="rgb_array"``: ``render()`` returns a ``render_size`` square frame of ``camera`` (for
        evaluation videos; renders offscreen, so the GL backend is chosen first, as for camera observations)."""
        if obs not in OBS_MODES:
            raise ValueError(f"robosuite obs = {obs!r}: expected one of {', '.join(map(repr, OBS_MODES))}")
        if isinstance(image_size, bool) or not isinstance(image_size, int) or image_size <= 0:
            raise ValueError(f"robosuite image_size = {image_size!r}: expected a positive integer (pixels per side)")
        if instruction_tokens is not None and not isinstance(instruction_tokens, bool):
            raise ValueError(f"robosuite instruction_tokens = {instruction_tokens!r}: expected true or false")
        self.obs_mode = obs
        self.camera = camera
        self.instruction = INSTRUCTIONS.get(task, "") if instruction is None else str(instruction)
        # tokens by default only with camera observations: a state policy learns one task, the instruction is constant
        with_tokens = obs == "rgb" if instruction_tokens is None else instruction_tokens
        if render_mode not in (None, "rgb_array"):
            raise ValueError(f"robosuite render_mode = {render_mode!r}: only \"rgb_array\" is supported")
        self.render_mode, self.render_size = render_mode, int(render_size)
        renders = obs == "rgb" or render_mode == "rgb_array"
        if renders:
            from ebrl.envs.render import choose_gl

            gl = choose_gl()  # before robosuite imports mujoco, whose GL backend is fixed on import
        robosuite, macros = _import_robosuite()
        if renders:
            _use_gl(gl)
        options = _make_options(horizon, obs, camera, image_size, renders, kwargs)
        try:
            self.env = robosuite.make(task, **options)
        except ValueError as exc:  # robosuite's word for an unknown camera is "invalid sensor"
            if obs == "rgb" and f"{camera}_image" in str(exc):
                raise ValueError(f"robosuite camera = {camera!r}: {task} has no such camera ({exc})") from exc
            raise
        self.horizon = horizon
        self._upside_down = macros.IMAGE_CONVENTION == "opengl"  # MuJoCo renders bottom row first
        self._tokens = tokenize(self.instruction)
        low, high = self.env.action_spec
        self.action_space = gym.spaces.Box(low.astype(np.float32), high.astype(np.float32), dtype=np.float32)
        self.obs_layout = self._layout(self.env.reset(), with_tokens)
        self.observation_space = gym.spaces.Box(-np.inf, np.inf, (self.obs_layout.size,), dtype=np.float32)
        self.t = 0
        self.skip_observation = False  # set by the env worker on steps whose observation nobody reads
        if obs == "rgb":  # the camera renders on demand (observe), never inside env.step
            self.env.modify_observable(f"{camera}_image", "enabled", False)

    def _layout(self, raw: dict[str, np.ndarray], with_tokens: bool) -> ObsLayout:
        proprio = np.size(raw[PROPRIO_KEY])
        if self.obs_mode == "rgb":
            height, width, channels = raw[f"{self.camera}_image"].shape
            fields = [ObsField("image", "image", (channels, height, width), uint8=True),  # rendered pixels / 255
                      ObsField("proprio", "vector", (proprio,))]
        else:
            fields = [ObsField("state", "vector", (proprio + np.size(raw[OBJECT_KEY]),))]
        if with_tokens:
            fields.append(ObsField("instruction", "tokens", self._tokens.shape))
        return ObsLayout(tuple(fields))

    def _obs(self, raw: dict[str, np.ndarray]) -> np.ndarray:
        if self.obs_mode == "rgb":
            image = raw.get(f"{self.camera}_image")  # (H, W, 3) uint8; absent while the camera is off
            if image is None:
                parts = {"image": np.zeros(self.obs_layout.fields[0].shape, np.float32)}
            else:
                parts = {"image": (image[::-1] if self._upside_down else image).transpose(2, 0, 1) / np.float32(255)}
            parts["proprio"] = raw[PROPRIO_KEY]
        else:
            parts = {"state": np.concatenate([np.ravel(raw[PROPRIO_KEY]), np.ravel(raw[OBJECT_KEY])])}
        parts["instruction"] = self._tokens  # packed only if the layout has the field
        return self.obs_layout.pack(parts)

    def reset(self, *, seed: int | None = None, options: dict | None = None):
        super().reset(seed=seed)
        if seed is not None:
            np.random.seed(seed)  # robosuite's placement samplers and joint noise draw from numpy's global generator
        self.t = 0
        raw = self.env.reset()
        return (self.observe() if self.obs_mode == "rgb" else self._obs(raw)), {}

    def step(self, action):
        raw, reward, _, info = self.env.step(np.asarray(action, dtype=np.float64))
        self.t += 1
        info = dict(info, success=bool(self.env._check_success()))
        obs = self.observe() if self.obs_mode == "rgb" and not self.skip_observation else self._obs(raw)
        return obs, float(reward), False, self.t >= self.horizon, info

    def observe(self) -> np.ndarray:
        """The full observation of the current state; with a camera, renders it now."""
        if self.obs_mode != "rgb":
            return self._obs(self.env._get_observations())
        name = f"{self.camera}_image"
        self.env.modify_observable(name, "enabled", True)
        try:
            return self._obs(self.env._get_observations(force_update=True))
        finally:
            self.env.modify_observable(name, "enabled", False)

    def render(self) -> np.ndarray | None:
        """With ``render_mode="rgb_array"``: the current state seen by ``camera``, (H, W, 3) uint8, right side up."""
        if self.render_mode != "rgb_array":
            return None
        frame = self.env.sim.render(camera_name=self.camera, width=self.render_size, height=self.render_size)
        return np.ascontiguousarray(frame[::-1] if self._upside_down else frame)

    def close(self) -> None:
        self.env.close()


def build(spec: EnvSpec) -> RobosuiteEnv:
    """The backend's builder (ebrl/envs/backends.py): episodes end at ``max_episode_steps``, else DEFAULT_HORIZON."""
    return RobosuiteEnv(spec.id, horizon=spec.max_episode_steps or DEFAULT_HORIZON, **spec.kwargs)


def _import_robosuite() -> tuple[Any, Any]:
    """robosuite and its ``macros``, imported quietly (its logger at ERROR) and without the ``MUJOCO_GL=egl`` its
    import sets for the whole process and every child it starts: the variable is put back as it was."""
    gl_before = os.environ.get("MUJOCO_GL")
    try:
        logging.getLogger("robosuite_logs").setLevel(logging.ERROR)
        import robosuite
        from robosuite import macros
    except ImportError as exc:
        raise ImportError(f"env.backend = 'robosuite' needs robosuite ({exc})") from exc
    finally:
        if gl_before is None:
            os.environ.pop("MUJOCO_GL", None)
        else:
            os.environ["MUJOCO_GL"] = gl_before
    return robosuite, macros


def _make_options(horizon: int, obs: str, camera: str, image_size: int, renders: bool,
                  kwargs: dict[str, Any]) -> dict[str, Any]:
    """``robosuite.make``'s options: a Panda, no on-screen viewer, shaped rewards at 20 Hz, episodes that never end
    inside robosuite (the env truncates them at ``horizon``); an offscreen renderer where anything ``renders``, the
    camera observable for ``obs = "rgb"``; then the user's ``kwargs``, which override any of them."""
    options = dict(robots="Panda", has_renderer=False, has_offscreen_renderer=False, use_camera_obs=False,
                   reward_shaping=True, control_freq=20, horizon=horizon, ignore_done=True,
                   hard_reset=False)  # a hard reset rebuilds the MuJoCo model: ~10x a step, every episode
    if renders:
        options.update(has_offscreen_renderer=True)
    if obs == "rgb":
        options.update(has_offscreen_renderer=True, use_camera_obs=True, use_object_obs=False,
                       camera_names=camera, camera_heights=image_size, camera_widths=image_size,
                       camera_depths=False)
    options.update(kwargs)
    return options


def _use_gl(backend: str) -> None:
    # robosuite builds its render context from binding_utils._MUJOCO_GL, read from MUJOCO_GL when robosuite was
    # first imported (and set to "egl" there when unset). In a process that imported robosuite before the backend
    # was chosen (a state env, a test run) that value is stale; contexts are built lazily, on the first camera
    # observation, so setting it here still takes effect, as long as no other GL platform was loaded meanwhile.
    from robosuite.utils import binding_utils

    if getattr(binding_utils, "_MUJOCO_GL", backend) != backend:
        binding_utils._MUJOCO_GL = backend
