"""What every simulator backend shares: building, describing, the preflight check. Which module builds each
``env.backend`` (imported on first use, so importing ebrl.envs imports no simulator), and every other fact of a
backend, is its record's (:mod:`ebrl.envs.records`)."""

from __future__ import annotations

import inspect
import math
from types import ModuleType
from typing import Any

import gymnasium as gym

from ebrl.envs.dictobs import SUPPORTED, DictObservation, field_of, leaves
from ebrl.envs.latency import StepLatency
from ebrl.envs.obs import ObsLayout
from ebrl.envs.records import BACKENDS, Backend, UnknownBackend, backend_record  # BACKENDS: re-exported
from ebrl.envs.render import RenderingUnavailable, ensure_gl_for
from ebrl.envs.spec import EnvError, EnvInfo, EnvSpec


def backend(spec: EnvSpec) -> Backend:
    """The record of ``spec.backend`` (:mod:`ebrl.envs.records`); EnvError naming the choices where none has it."""
    try:
        return backend_record(spec.backend)
    except UnknownBackend as exc:
        raise EnvError(str(exc)) from None


def backend_module(spec: EnvSpec) -> ModuleType:
    """The module that builds ``spec``'s environment, imported now (the simulator itself may wait until build)."""
    return backend(spec).load()


def make_env(spec: EnvSpec, seed: int = 0) -> gym.Env:
    """Build the environment with its backend, check its spaces, and add the configured step latency. A builder
    that takes ``seed`` (the worker's) is given it: LIBERO picks each env's task by it."""
    build = backend_module(spec).build
    try:
        env: gym.Env = build(spec, seed=seed) if "seed" in inspect.signature(build).parameters else build(spec)
    except Exception as exc:  # gymnasium, the simulators and user modules raise many kinds
        raise EnvError(f"env.id = {spec.id!r} (backend {spec.backend}): {type(exc).__name__}: {exc}") from exc
    check_spaces(spec.id, env.observation_space, env.action_space)
    if isinstance(env.observation_space, gym.spaces.Dict):
        env = DictObservation(env, spec.obs_keys, spec.id)
    elif spec.obs_keys:
        raise EnvError(f"env.obs_keys = {list(spec.obs_keys)} selects keys of a Dict observation; {spec.id}'s "
                       f"observation space is {env.observation_space}")
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
    """EnvError naming the space and what EBRL supports, for spaces it cannot read or drive."""
    if isinstance(obs_space, gym.spaces.Dict):
        for path, leaf in leaves(obs_space).items():
            field_of(path, leaf, env_id)
    elif not isinstance(obs_space, gym.spaces.Box):
        raise EnvError(f"{env_id}: observation space {obs_space} is not supported: EBRL reads a Box (flat or image "
                       f"arrays) or a Dict, nested too, whose leaves are {SUPPORTED}")
    if not isinstance(act_space, gym.spaces.Box) or len(act_space.shape) != 1:
        hint = (" (discrete actions are not: EBRL's policies output chunks of continuous actions)"
                if isinstance(act_space, (gym.spaces.Discrete, gym.spaces.MultiDiscrete, gym.spaces.MultiBinary))
                else " (a Box of another shape: flatten it to 1-d)" if isinstance(act_space, gym.spaces.Box) else "")
        raise EnvError(f"{env_id}: action space {act_space} is not supported: EBRL drives continuous actions, a 1-d "
                       f"Box (low, high, (n,)){hint}; wrap the env so that its action space is one")


def describe(spec: EnvSpec) -> EnvInfo:
    """Build the environment once, read what policies need to know, close it. An environment may declare
    ``obs_layout`` (an :class:`ObsLayout`) and ``instruction``; otherwise its Box shape decides the layout."""
    env = make_env(spec)
    try:
        base = env.unwrapped
        layout = _declared_layout(env) or ObsLayout.for_shape(env.observation_space.shape)
        if layout.size != math.prod(env.observation_space.shape):
            raise EnvError(f"{spec.id}: obs_layout {layout.describe()} has {layout.size} values, "
                           f"the observation space {env.observation_space.shape}")
        return EnvInfo(env.observation_space, env.action_space, layout, getattr(base, "instruction", ""),
                       declared_reward_range(base))
    finally:
        env.close()


def declared_reward_range(env: Any) -> tuple[float, float] | None:
    """The range of one step's reward that ``env`` declares (``reward_range``: gym's attribute, which gymnasium
    1.x dropped; EBRL's MuJoCo tasks declare theirs), where it is a finite ``(low, high)``; else None."""
    declared = getattr(env, "reward_range", None)
    try:
        low, high = (float(v) for v in declared)  # type: ignore[union-attr]
    except (TypeError, ValueError):
        return None
    return (low, high) if math.isfinite(low) and math.isfinite(high) and low <= high else None


def _declared_layout(env: gym.Env) -> ObsLayout | None:
    """The ``obs_layout`` of the outermost wrapper or env that declares one (the Dict adapter's, the env's own)."""
    try:
        return env.get_wrapper_attr("obs_layout")
    except AttributeError:
        return None


def lazy_observer(env: gym.Env) -> gym.Env | None:
    """What skips rendering the observations nobody reads (``skip_observation``) and renders the current one on
    demand (``observe()``), ebrl/envs/worker.py: the env itself (robosuite's, a user's), seen through the Dict
    adapter when one converts its observations; None for an env that cannot."""
    base = env.unwrapped
    if not (callable(getattr(base, "observe", None)) and hasattr(base, "skip_observation")):
        return None
    while isinstance(env, gym.Wrapper) and not isinstance(env, DictObservation):
        env = env.env
    return env if isinstance(env, DictObservation) else base
