"""The simulator backends: which module builds each ``env.backend`` (imported on first use, so importing
ebrl.envs imports no simulator), and what every backend shares: building, describing, the preflight check."""

from __future__ import annotations

import importlib
import math
from dataclasses import dataclass
from types import ModuleType

import gymnasium as gym

from ebrl.envs.latency import StepLatency
from ebrl.envs.obs import ObsLayout
from ebrl.envs.render import RenderingUnavailable, ensure_gl_for
from ebrl.envs.spec import EnvError, EnvInfo, EnvSpec


@dataclass(frozen=True)
class Backend:
    """Where one ``env.backend`` lives. Its module defines ``build(spec) -> gym.Env`` and may define
    ``preflight(spec)``, which raises EnvError when the simulator cannot run on this machine."""

    module: str
    preload: tuple[str, ...]  # what the env workers' forkserver imports once, before it forks them (worker.py)


# the config's env.backend names (ebrl/config.py); tests/test_envs.py checks the two agree
BACKENDS: dict[str, Backend] = {
    "gymnasium": Backend("ebrl.envs.gym", ("gymnasium", "mujoco")),
    "robosuite": Backend("ebrl.envs.robosuite", ("gymnasium", "mujoco", "robosuite")),
    "maniskill": Backend("ebrl.envs.maniskill", ("gymnasium", "torch", "mani_skill.envs")),
    "mjwarp": Backend("ebrl.envs.mjwarp", ("gymnasium", "mujoco")),  # a group is one batch; one env: CPU MuJoCo
}


def backend(spec: EnvSpec) -> Backend:
    if spec.backend not in BACKENDS:
        raise EnvError(f"env.backend = {spec.backend!r}: expected one of {', '.join(map(repr, BACKENDS))}")
    return BACKENDS[spec.backend]


def backend_module(spec: EnvSpec) -> ModuleType:
    """The module that builds ``spec``'s environment, imported now (the simulator itself may wait until build)."""
    return importlib.import_module(backend(spec).module)


def make_env(spec: EnvSpec, seed: int = 0) -> gym.Env:
    """Build the environment with its backend, check its spaces, and add the configured step latency."""
    build = backend_module(spec).build
    try:
        env: gym.Env = build(spec)
    except Exception as exc:  # gymnasium, the simulators and user modules raise many kinds
        raise EnvError(f"env.id = {spec.id!r} (backend {spec.backend}): {type(exc).__name__}: {exc}") from exc
    check_spaces(spec.id, env.observation_space, env.action_space)
    if spec.latency == "lognormal":
        env = StepLatency(env, spec.latency_mean_ms, spec.latency_sigma, seed=seed)
    return env


def preflight(spec: EnvSpec) -> None:
    """Fail fast, before any process starts, when the simulator cannot run on this machine (raises EnvError).
    Camera observations also decide the offscreen GL backend here, once, for every process of the run."""
    check = getattr(backend_module(spec), "preflight", None)
    if check is not None:
        check(spec)
    try:
        ensure_gl_for(spec)
    except RenderingUnavailable as exc:
        raise EnvError(f"env.id = {spec.id!r} (backend {spec.backend}): {exc}") from None


def check_spaces(env_id: str, obs_space: gym.Space, act_space: gym.Space) -> None:
    if not isinstance(obs_space, gym.spaces.Box):
        raise EnvError(f"{env_id}: observation space {obs_space} is not a Box (flat or image arrays are supported)")
    if not isinstance(act_space, gym.spaces.Box) or len(act_space.shape) != 1:
        raise EnvError(f"{env_id}: action space {act_space} is not a 1-d Box (continuous actions are supported)")


def describe(spec: EnvSpec) -> EnvInfo:
    """Build the environment once, read what policies need to know, close it. An environment may declare
    ``obs_layout`` (an :class:`ObsLayout`) and ``instruction``; otherwise its Box shape decides the layout."""
    env = make_env(spec)
    try:
        base = env.unwrapped
        layout = getattr(base, "obs_layout", None) or ObsLayout.for_shape(env.observation_space.shape)
        if layout.size != math.prod(env.observation_space.shape):
            raise EnvError(f"{spec.id}: obs_layout {layout.describe()} has {layout.size} values, "
                           f"the observation space {env.observation_space.shape}")
        return EnvInfo(env.observation_space, env.action_space, layout, getattr(base, "instruction", ""))
    finally:
        env.close()
