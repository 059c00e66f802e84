"""The ``mjwarp`` backend: a group's environments as one MuJoCo Warp model of ``sim.envs_per_group`` worlds,
stepped together on the GPU (or the CPU), for any :class:`~ebrl.envs.mjtask.MjTask` (``env.id``: a shipped task such
as ``"PandaPickCube-v0"``, or ``"my_pkg.tasks:MyTask"``).

A group is always vectorized (ebrl/envs/vector.py): :class:`MjWarpBatch` is its batch. The worlds' state stays on the
device for the whole chunk: the task's action, reward, success and observation functions run as torch operations
on views of MuJoCo Warp's arrays (``wp.to_torch``, no copy), the physics steps of one env step are one CUDA graph
launch, and only the chunk's results travel to the host at its end (:class:`~ebrl.envs.batch.BatchRunner`). Each
world starts episode ``k`` from the state the task draws from seed ``seeds[i] + 7919 k``, on the host, as a CPU env
worker seeded ``seeds[i]`` would: a batch replays what the same envs on CPU MuJoCo start from.

``env.kwargs`` the batch takes (the rest go to the task's constructor):

* ``device``: ``"auto"`` (default: ``cuda`` where torch sees a CUDA GPU, else ``cpu``), ``"cpu"``, ``"cuda"`` or
  ``"cuda:N"``;
* ``nconmax``: contacts per world to allocate (default 32), ``njmax``: constraint rows per world (default 128;
  PandaPickCube, pressed into the table by random actions on CPU MuJoCo, peaks at 9 and 44: a test keeps 2x). A
  step that needs more stops the group with an error saying which to raise: MuJoCo Warp would drop contacts;
* ``cuda_graph``: capture an env step's physics steps, and a reset's clearing and forward pass, as graphs (default
  true): CUDA graphs on the GPU; on the CPU Warp's own graph replay (Warp >= 1.13), which skips Python's launch
  overhead (2.4x an env step of 64 worlds). Where capture fails the launches run one by one, with a warning.

Where this module runs without the GPU batch (the launcher's preflight, gen and train describing the task, the
evaluation service), the task's CPU MuJoCo version stands in (:func:`build`): same model, same spaces, same reward.
MuJoCo Warp compiles its kernels on first use (about 20 s for PandaPickCube on 2 CPU cores) into Warp's kernel
cache (``WARP_CACHE_PATH``, default ``~/.cache/warp``); later runs load them from there.
"""

from __future__ import annotations

import importlib.util
from typing import Any

import gymnasium as gym

from ebrl import devices
from ebrl.envs.mjtask import MjTaskEnv, make_task
from ebrl.envs.records import MJWARP
from ebrl.envs.spec import EnvError, EnvSpec

BATCH_KWARGS = {"device": "auto", "nconmax": 32, "njmax": 128, "cuda_graph": True}


def split_kwargs(kwargs: dict[str, Any]) -> tuple[dict[str, Any], dict[str, Any]]:
    """``env.kwargs`` as (the batch's own, with defaults; the task's)."""
    own = {key: kwargs.get(key, default) for key, default in BATCH_KWARGS.items()}
    for key in ("nconmax", "njmax"):
        if isinstance(own[key], bool) or not isinstance(own[key], int) or own[key] <= 0:
            raise EnvError(f"env.kwargs.{key} = {own[key]!r}: expected a positive integer")
    if not isinstance(own["cuda_graph"], bool):
        raise EnvError(f"env.kwargs.cuda_graph = {own['cuda_graph']!r}: expected true or false")
    try:
        devices.check_syntax(str(own["device"]), "env.kwargs.device")
    except devices.DeviceError as exc:
        raise EnvError(str(exc)) from None
    return own, {key: value for key, value in kwargs.items() if key not in BATCH_KWARGS}


def resolve_device(device: str) -> str:
    """Where the worlds step (``"cpu"`` or ``"cuda:N"``): ``auto`` is the GPU where torch sees one, else the CPU."""
    try:
        return str(devices.resolve(device, "env.kwargs.device"))
    except devices.DeviceError as exc:
        raise EnvError(str(exc)) from None


def build(spec: EnvSpec) -> gym.Env:
    """One world on CPU MuJoCo (the backend's single env: describing the task, evaluation), time-limited as a
    batch world is; ``env.kwargs.render_mode`` (evaluation videos) reaches the env, the batch's keys do not."""
    kwargs = dict(spec.kwargs)
    render_mode = kwargs.pop("render_mode", None)
    task = make_task(spec.id, split_kwargs(kwargs)[1])
    env = MjTaskEnv(task, render_mode=render_mode)
    return gym.wrappers.TimeLimit(env, spec.max_episode_steps or task.max_episode_steps)


def preflight(spec: EnvSpec) -> None:
    """Fail before any process starts: MuJoCo Warp missing, an unknown task or keyword, CUDA asked for and absent."""
    own, task_kwargs = split_kwargs({k: v for k, v in spec.kwargs.items() if k != "render_mode"})
    where = f"env.id = {spec.id!r} (backend mjwarp)"
    missing = [name for name in ("warp", "mujoco_warp") if importlib.util.find_spec(name) is None]
    if missing:
        raise EnvError(f"{where}: MuJoCo Warp is not installed ({', '.join(missing)} missing); {MJWARP.install}")
    make_task(spec.id, task_kwargs)  # an unknown task or keyword fails here, naming it
    if own["device"] != "auto":
        resolve_device(own["device"])  # a CUDA device torch does not see here fails, naming the field
