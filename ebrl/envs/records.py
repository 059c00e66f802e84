"""The simulator backends as records: each ``env.backend`` is one :class:`Backend` that owns every fact EBRL asks
of it, and :data:`BACKENDS` is their registry (the config's choices of ``env.backend`` come from it).

Callers ask the record (``backend_record(cfg.env.backend).vectorized(...)``) and never test a backend's name
(tests/test_architecture.py checks it). The records are light (this module imports ebrl.devices alone, and no
simulator or torch), so the config, the launcher and the hosts' plan ask them; what a backend builds lives in its
module (``Backend.module``), imported on first use.

Adding a backend: docs/contributing.md: "A new simulator backend".
"""

from __future__ import annotations

import importlib
from collections.abc import Callable, Mapping
from dataclasses import dataclass
from types import ModuleType
from typing import Any, Literal

from ebrl import devices

Kwargs = Mapping[str, Any]  # env.kwargs


class UnknownBackend(ValueError):
    """An ``env.backend`` that no record has; the message names the choices."""


def _cpu_only(kwargs: Kwargs) -> bool:
    return False


@dataclass(frozen=True)
class Backend:
    """One ``env.backend``: where it is built, and what the config, the launcher, the sim service and the
    scheduler need to know of it without building it."""

    name: str  # env.backend
    # defines build(spec) -> gym.Env (build(spec, seed) where the worker's seed picks something), and may define
    # preflight(spec), which raises EnvError when the simulator cannot run on this machine (ebrl.envs.backends)
    module: str
    preload: tuple[str, ...]  # what the env workers' forkserver imports once, before it forks them (worker.py)
    label: str  # the simulator's own name, in messages
    ids: str = ""  # what env.id names under it, in the config's docs
    options: str = ""  # the env.kwargs it takes, in the config's docs; "": its environment's own
    about: str = ""  # what env.backend's config docs say of it ("{install}": its install hint); "": nothing
    install: str = ""  # what installs it, in its errors; "": installed with EBRL
    # what sim.vectorized = "auto" means for it: "always" (a group is one batch by nature, and false is refused:
    # always_vectorized says why and what to use instead), "gpu_physics" (where its physics is on the GPU), or
    # "never" (a group is vectorized only when sim.vectorized = true: copies of the env stepped in one process)
    vectorize: Literal["always", "gpu_physics", "never"] = "never"
    always_vectorized: str = ""
    gpu_physics: Callable[[Kwargs], bool] = _cpu_only  # whether its worlds step on the GPU, given env.kwargs
    # "module:callable" making its own batch (spec, seeds) for a group it vectorizes itself; "": copies of the env
    batch: str = ""
    obs_default: str = "state"  # env.kwargs.obs where absent: "rgb" is camera observations
    gl_cameras: bool = False  # its camera observations render with MuJoCo's offscreen GL (ebrl.envs.render)
    gl_frames: bool = True  # its render_mode = "rgb_array" frames (evaluation videos) render with MuJoCo's GL
    # "module:mapping" of the tasks EBRL ships for it, where it is a GPU simulator whose worlds step on the GPU
    # with env code EBRL ships: then sim, gen and train may share one process on a GPU host (hosts.decide_processes)
    gpu_tasks: str = ""
    # where its physics could be on the GPU: what runs instead on the CPU, said where its configs (sized for GPU
    # physics) would start a worker process per env (ebrl.prepare.too_many_processes); None: never said
    on_cpu: Callable[[Kwargs], str] | None = None
    suites: bool = False  # env.id names a benchmark suite that `ebrl eval PATH --suite` runs (ebrl.evaluate_suite)

    def load(self) -> ModuleType:
        """The module that builds its environments, imported now (the simulator itself may wait until build)."""
        return importlib.import_module(self.module)

    def vectorized(self, setting: bool | str, kwargs: Kwargs) -> bool:
        """Whether each sim group is one vectorized process, under ``sim.vectorized = setting``."""
        if self.vectorize == "always":
            return True
        if setting == "auto":
            return self.vectorize == "gpu_physics" and self.gpu_physics(kwargs)
        return bool(setting)

    def batch_maker(self, kwargs: Kwargs) -> Callable[[Any, list[int]], Any] | None:
        """What makes a vectorized group's batch ``(spec, seeds)`` in its own simulator (MuJoCo Warp's worlds,
        ManiSkill's under GPU PhysX): where it vectorizes by itself; None: copies of the env in one process."""
        if not self.batch or not self.vectorized("auto", kwargs):
            return None
        return _attribute(self.batch)

    def cameras(self, kwargs: Kwargs) -> bool:
        """Whether ``env.kwargs`` asks for camera observations (``obs = "rgb"``, or absent where that is its
        default)."""
        return kwargs.get("obs", self.obs_default) == "rgb"

    @property
    def gpu_simulator(self) -> bool:
        """Whether it is a GPU simulator with env code EBRL ships (:attr:`gpu_tasks`)."""
        return bool(self.gpu_tasks)

    def ships(self, env_id: str) -> bool:
        """Whether ``env_id`` is one of the tasks EBRL ships for it (:attr:`gpu_tasks`), not a user's module; imports
        where they are listed (MuJoCo: only where a GPU simulator is about to run)."""
        return bool(self.gpu_tasks) and env_id in _attribute(self.gpu_tasks)


def _attribute(path: str) -> Any:
    """The object a ``"module:name"`` path names, its module imported now."""
    module, _, name = path.partition(":")
    return getattr(importlib.import_module(module), name)


def _cuda_device(kwargs: Kwargs) -> bool:
    # MuJoCo Warp on a CUDA env.kwargs.device ("auto", its default: where torch sees one)
    return devices.is_cuda(str(kwargs.get("device", "auto")))


def _physx_cuda(kwargs: Kwargs) -> bool:
    # ManiSkill under sim_backend = "physx_cuda[:N]", or "auto" where torch sees a CUDA GPU (devices.physx_backend)
    return devices.physx_backend(kwargs.get("sim_backend")).startswith("physx_cuda")


def _cpu_physx(kwargs: Kwargs) -> str:
    return (f"ManiSkill envs on CPU PhysX (env.kwargs.sim_backend = {kwargs.get('sim_backend', 'physx_cpu')!r}: no "
            "GPU PhysX here)")


GYMNASIUM = Backend("gymnasium", "ebrl.envs.gym", ("gymnasium", "mujoco"), "Gymnasium",
                    ids="a gymnasium id (InvertedPendulum-v5, my_pkg.envs:MyEnv-v0)")
ROBOSUITE = Backend("robosuite", "ebrl.envs.robosuite", ("gymnasium", "mujoco", "robosuite"), "robosuite",
                    ids="a robosuite task (Lift, PickPlaceCan, Stack)", gl_cameras=True,
                    options="obs = \"state\" | \"rgb\", image_size, camera, instruction, ...")
MANISKILL = Backend(
    "maniskill", "ebrl.envs.maniskill", ("gymnasium", "torch", "mani_skill.envs"), "ManiSkill",
    ids="a ManiSkill task (PickCube-v1)",
    options="obs = \"state\" | \"rgb\", image_size, sim_backend, control_mode, ...",
    about="the optional extra, `{install}`, needs a Vulkan GPU", install="pip install -e '.[maniskill]'",
    vectorize="gpu_physics", gpu_physics=_physx_cuda, batch="ebrl.envs.batch:maniskill_batch",
    gl_frames=False, on_cpu=_cpu_physx)  # SAPIEN renders, on Vulkan (its preflight checks it)
MJWARP = Backend(
    # a group is one batch; one env: CPU MuJoCo. A group imports torch and Warp in its own process: preloaded in the
    # forkserver they brought the first env step 0.7 s sooner, but the groups then took the cores from training in
    # a shared process on 2 CPU cores (PandaPickCube seed 0, 70 updates: 2,504 decisions too stale to learn from
    # and success 0.0, against 96 and 0.65 without)
    "mjwarp", "ebrl.envs.mjwarp", ("gymnasium", "mujoco"), "MuJoCo Warp",
    ids="an mjwarp task (PandaPickCube-v0, my_pkg.tasks:MyTask)",
    options="device, nconmax, njmax, cuda_graph, then the task's own, e.g. model",
    about="MuJoCo Warp, `{install}`, each group one batch of envs_per_group worlds on the GPU or the CPU, "
          "env.kwargs.device", install="pip install -e '.[mjwarp]'",
    vectorize="always", gpu_physics=_cuda_device, batch="ebrl.envs.batch:MjWarpBatch",
    gpu_tasks="ebrl.envs.mjtask:TASKS",
    always_vectorized="an mjwarp group is one MuJoCo Warp model of envs_per_group worlds; for one CPU MuJoCo env per "
                      "worker process use env.backend = \"gymnasium\" with env.id = "
                      "\"ebrl.envs.tasks:PandaPickCube-v0\" (or your task through ebrl.envs.mjtask.MjTaskEnv)")
LIBERO = Backend(
    # LIBERO itself is imported by each worker (quietly, ebrl.envs.libero): ~14 MB over robosuite
    "libero", "ebrl.envs.libero", ("gymnasium", "mujoco", "robosuite", "ebrl.envs.libero"), "LIBERO",
    ids="a LIBERO suite (libero_spatial, libero_object, libero_goal, libero_10, libero_90)",
    options="tasks (an index, a name or a list; empty: the whole suite spread over the envs), obs = \"rgb\" | "
            "\"state\", cameras, image_size, no_op_steps, init_states, arena_mb, object_state_size",
    about="the LIBERO benchmark, `make libero`",
    install="`make libero`, or `pip install -e '.[libero]'` then `ebrl libero setup`",
    obs_default="rgb", gl_cameras=True, suites=True)  # its cameras are on by default

# the registry: env.backend's choices (ebrl/config/rollout.py), in this order
BACKENDS: dict[str, Backend] = {record.name: record for record in (GYMNASIUM, ROBOSUITE, MANISKILL, MJWARP, LIBERO)}


def backend_record(name: str) -> Backend:
    """The record of ``env.backend = name``; :class:`UnknownBackend` naming the choices where none has it."""
    if name not in BACKENDS:
        raise UnknownBackend(f"env.backend = {name!r}: expected one of {', '.join(map(repr, BACKENDS))}")
    return BACKENDS[name]


def described() -> str:
    """What env.backend's config docs say of the backends: each that says something of itself (``about``)."""
    return "; ".join(f"{r.name}: {r.about.format(install=r.install)}" for r in BACKENDS.values() if r.about)


def described_ids() -> str:
    """What env.id's config docs say it names: each backend's ``ids``."""
    ids = [r.ids for r in BACKENDS.values() if r.ids]
    return ", ".join(ids[:-1]) + " or " + ids[-1] if len(ids) > 1 else "".join(ids)


def described_options() -> str:
    """What env.kwargs' config docs say each backend takes: its ``options``."""
    return "; ".join(f"{r.label}: {r.options}" for r in BACKENDS.values() if r.options)
