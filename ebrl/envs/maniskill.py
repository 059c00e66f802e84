"""ManiSkill3 adapter: one task (PickCube-v1, PushCube-v1, StackCube-v1, ...) as a gymnasium environment.

One environment per worker process (``num_envs = 1``); ManiSkill's batched torch
tensors become one flat float32 numpy vector, laid out by ``obs_layout``:

- ``obs = "state"``: ``state`` = ManiSkill's flat state observation (robot
  proprioception, task extras and privileged object poses), plus the
  ``instruction`` tokens if asked for;
- ``obs = "rgb"``: ``image`` (3, H, W) from one camera in [0, 1], ``proprio`` =
  ``obs["agent"]`` (qpos, qvel) followed by ``obs["extra"]`` (the task's vectors,
  e.g. the TCP pose and the goal position, which the cameras do not show), as
  ManiSkill's own RGB baselines flatten them, and the ``instruction`` tokens.

Reward is the task's ``normalized_dense`` reward; ``terminated`` is ManiSkill's
(success, or failure where a task defines it), ``truncated`` its time limit, and
``info["success"]`` the task's own success check.

ManiSkill renders with SAPIEN, which needs a Vulkan device even for state
observations: a GPU, or a software driver SAPIEN accepts (Mesa 25's lavapipe
does, Debian 12's Mesa 22.3 does not). :func:`preflight` says in a second or
less, before any process starts, when there is none, instead of a worker
failing deep inside SAPIEN. GPU PhysX (``sim_backend = "physx_cuda"``) also needs SAPIEN's GPU PhysX library,
which SAPIEN downloads from GitHub at first use: :func:`check_physx_gpu` says at once, before a worker's download
fails, where it is missing and cannot be fetched.
"""

from __future__ import annotations

import glob
import importlib.metadata
import importlib.util
import json
import logging
import os
import platform
import socket
import subprocess
import sys
import threading
import urllib.parse
from collections.abc import Callable, Mapping
from dataclasses import dataclass
from pathlib import Path
from typing import Any

import gymnasium as gym
import numpy as np

from ebrl import devices
from ebrl.envs.obs import ObsField, ObsLayout, tokenize
from ebrl.envs.records import MANISKILL
from ebrl.envs.spec import EnvError, EnvSpec

OBS_MODES = ("state", "rgb")
SIM_BACKENDS = ("physx_cpu", "physx_cuda", "auto")  # "physx_cuda:N" picks GPU N; auto: physx_cuda where CUDA is
# ManiSkill's PPO baselines use joint deltas, and every robot it ships supports them (end-effector modes vary)
DEFAULT_CONTROL_MODE = "pd_joint_delta_pos"
DEFAULT_IMAGE_SIZE = 64
# what each task asks for, with the objects' colours as ManiSkill 3.0.1 builds them (envs/tasks/tabletop/*.py)
INSTRUCTIONS = {
    "PickCube-v1": "pick up the red cube and move it to the goal",
    "PushCube-v1": "push the blue cube to the goal region",
    "PullCube-v1": "pull the blue cube to the goal region",
    "StackCube-v1": "stack the red cube on top of the green cube",
    "PokeCube-v1": "use the peg to push the red cube to the goal",
    "LiftPegUpright-v1": "lift the peg and stand it upright",
    "PegInsertionSide-v1": "insert the peg into the hole from the side",
    "PlaceSphere-v1": "place the sphere into the bin",
    "RollBall-v1": "roll the ball to the goal region",
    "PushT-v1": "push the T block onto the target",
    "PlugCharger-v1": "plug the charger into the receptacle",
}

SKIP_PREFLIGHT_VAR = "EBRL_MANISKILL_SKIP_PREFLIGHT"
CPU_CONFIGS = ("configs/quickstart.toml", "configs/robosuite_lift.toml", "configs/robosuite_lift_rgb.toml")
# where the Vulkan loader looks for driver manifests (ICDs) on Linux, relative to the root
ICD_DIRS = ("etc/vulkan/icd.d", "usr/local/share/vulkan/icd.d", "usr/share/vulkan/icd.d")
# where SAPIEN's fallback ICD (an NVIDIA driver installed without its manifest) finds the driver's Vulkan library
NVIDIA_LIB = "libGLX_nvidia.so.0"
LIB_DIRS = ("usr/lib/x86_64-linux-gnu", "usr/lib64", "usr/lib", "usr/local/nvidia/lib64")
CPU_DRIVERS = ("lvp", "lavapipe", "llvmpipe", "swiftshader", "swrast")  # software Vulkan: not a GPU
# SAPIEN's GPU PhysX library, which sapien.physx.enable_gpu() loads from ~/.sapien/physx/<version>/ (Path.home(): $HOME)
# and, where it is not there, downloads from physx-precompiled's GitHub release of that version (sapien 3.0.3's
# sapien/physx/__init__.py); the version is sapien.physx.version(), built into SAPIEN, by SAPIEN release
PHYSX_GPU_LIB = "libPhysXGpu_64.so"
PHYSX_VERSIONS = {"3.0.3": "105.1-physx-5.3.1.patch0"}
PHYSX_PINNED = "3.0.3"  # pyproject's maniskill extra
PHYSX_URL = "https://github.com/sapien-sim/physx-precompiled/releases/download/{version}/{zip}"
PHYSX_HOST = ("github.com", 443)
PROBE_TIMEOUT = 2.0  # seconds for the reachability check of the download host, name lookup included
MJWARP_CONFIG = "configs/mjwarp_pickcube.toml"  # GPU-parallel physics without SAPIEN: MuJoCo Warp


def make_options(num_envs: int, max_episode_steps: int | None, obs: str, sim_backend: str | None, image_size: int,
                 control_mode: str, kwargs: dict[str, Any]) -> dict[str, Any]:
    """The ``gym.make`` keyword arguments of a ManiSkill task for the adapter's settings (``kwargs``: the caller's
    own, passed on)."""
    check_kwargs({"obs": obs, "image_size": image_size, "sim_backend": sim_backend, **kwargs})
    options: dict[str, Any] = dict(num_envs=num_envs, obs_mode=obs, reward_mode="normalized_dense",
                                   control_mode=control_mode, sim_backend=devices.physx_backend(sim_backend))
    if max_episode_steps:
        options["max_episode_steps"] = int(max_episode_steps)  # else the task's registered limit
    kwargs = dict(kwargs)
    if obs == "rgb":  # every camera at image_size, under the caller's own sensor_configs
        options["sensor_configs"] = {"width": image_size, "height": image_size, **kwargs.pop("sensor_configs", {})}
    options.update(kwargs)
    return options


def action_box(task: str, control_mode: str, env: gym.Env) -> gym.spaces.Box:
    """One environment's action space, as float32; a flat Box or a clear error."""
    space = env.unwrapped.single_action_space
    if not isinstance(space, gym.spaces.Box) or len(space.shape) != 1:
        raise EnvError(f"{task}: control_mode = {control_mode!r} gives the action space {space}; a flat Box is "
                       "supported (one robot, one controller)")
    return gym.spaces.Box(np.asarray(space.low, np.float32), np.asarray(space.high, np.float32), dtype=np.float32)


class ObsPacker:
    """ManiSkill's batched observations ([N, ...] torch tensors, on the sim's device) as EBRL's flat float32
    layout, [N, size], computed where they are (no copy to the host)."""

    def __init__(self, obs_mode: str, camera: str | None, instruction: str, with_tokens: bool, raw: Any):
        self.obs_mode, self.camera = obs_mode, camera
        self.tokens = _torch().as_tensor(tokenize(instruction)).float()
        parts = self.parts(raw)
        if obs_mode == "rgb":
            fields = [ObsField("image", "image", tuple(parts["image"].shape[1:])),
                      ObsField("proprio", "vector", (parts["proprio"].shape[1],))]
        else:
            fields = [ObsField("state", "vector", (parts["state"].shape[1],))]
        if with_tokens:
            fields.append(ObsField("instruction", "tokens", tuple(self.tokens.shape)))
        self.layout = ObsLayout(tuple(fields))

    def _image(self, raw: dict[str, Any]) -> Any:
        cameras = raw["sensor_data"]
        name = self.camera or next(iter(cameras))
        if name not in cameras:
            raise EnvError(f"ManiSkill camera = {name!r}: this task's cameras are {', '.join(cameras)}")
        image = _torch().as_tensor(cameras[name]["rgb"])  # (N, H, W, 3), uint8 in every shader pack
        scaled = image.float() / 255.0 if image.dtype == _torch().uint8 else image.float()
        return scaled.permute(0, 3, 1, 2)

    def parts(self, raw: Any) -> dict[str, Any]:
        """``{name: [N, ...]}``; the instruction tokens are packed only if the layout has the field."""
        if self.obs_mode == "rgb":
            image = self._image(raw)
            parts = {"image": image, "proprio": torch_cat([_flat(raw["agent"]), _flat(raw["extra"])], image.shape[0])}
        else:
            state = _torch().as_tensor(raw).float()
            parts = {"state": state.reshape(state.shape[0], -1)}
        return parts

    def pack(self, raw: Any) -> Any:
        """``[N, layout.size]`` float32, on the observations' device."""
        parts = self.parts(raw)
        n = next(iter(parts.values())).shape[0]
        device = next(iter(parts.values())).device
        flat = [parts[f.name].reshape(n, -1) if f.name in parts else self.tokens.to(device).expand(n, -1)
                for f in self.layout.fields]
        return torch_cat(flat, n)


class ManiSkillEnv(gym.Env):
    """One ManiSkill task. ``kwargs`` not named here go to ``gym.make`` (e.g. ``robot_uids``, ``render_backend``,
    ``sim_config``, ``reward_mode``)."""

    metadata = {"render_modes": []}

    def __init__(self, task: str, max_episode_steps: int | None = None, *, obs: str = "state",
                 sim_backend: str | None = None, image_size: int = DEFAULT_IMAGE_SIZE,
                 control_mode: str = DEFAULT_CONTROL_MODE, camera: str | None = None,
                 instruction: str | None = None, instruction_tokens: bool | None = None, **kwargs: Any):
        if "num_envs" in kwargs:
            raise EnvError("ManiSkill num_envs: the adapter runs one environment per worker process (or one "
                           "vectorized environment per group); set sim.envs_per_group instead")
        options = make_options(1, max_episode_steps, obs, sim_backend, image_size, control_mode, kwargs)
        self.instruction = INSTRUCTIONS.get(task, "") if instruction is None else str(instruction)
        # tokens by default only with camera observations: a state policy learns one task, the instruction is constant
        with_tokens = obs == "rgb" if instruction_tokens is None else bool(instruction_tokens)
        self.env = _make_maniskill(task, **options)
        self.sim_backend = options["sim_backend"]
        self.action_space = action_box(task, control_mode, self.env)
        raw, _ = self.env.reset()
        self.packer = ObsPacker(obs, camera, self.instruction, with_tokens, raw)
        self.obs_layout = self.packer.layout
        self.observation_space = gym.spaces.Box(-np.inf, np.inf, (self.obs_layout.size,), dtype=np.float32)

    def _obs(self, raw: Any) -> np.ndarray:
        return _numpy(self.packer.pack(raw))[0].astype(np.float32)

    def reset(self, *, seed: int | None = None, options: dict | None = None):
        super().reset(seed=seed)
        raw, info = self.env.reset(seed=seed, options=options)
        return self._obs(raw), _info(info)

    def step(self, action):
        raw, reward, terminated, truncated, info = self.env.step(np.asarray(action, dtype=np.float32))
        return self._obs(raw), float(_numpy(reward).reshape(-1)[0]), _bool(terminated), _bool(truncated), _info(info)

    def render(self) -> np.ndarray:
        """One RGB frame (H, W, 3) uint8, when built with ``render_mode="rgb_array"`` (evaluation videos)."""
        frame = _numpy(self.env.render())
        return frame[0] if frame.ndim == 4 else frame

    def close(self) -> None:
        self.env.close()


def build(spec: EnvSpec) -> ManiSkillEnv:
    """The backend's builder (ebrl/envs/backends.py): the task's own episode limit unless the spec sets one."""
    return ManiSkillEnv(spec.id, max_episode_steps=spec.max_episode_steps or None, **spec.kwargs)


def _make_maniskill(task: str, **kwargs: Any) -> gym.Env:
    """``gym.make`` of a ManiSkill task (the one place that imports ManiSkill; tests replace it with a fake). Under
    GPU PhysX, SAPIEN's GPU library is checked for first: a process started without the preflight still gets the
    clear error, not a failed download's stack trace."""
    check_physx_gpu(str(kwargs.get("sim_backend") or ""), f"env.id = {task!r} (backend maniskill)")
    import mani_skill.envs  # noqa: F401  registers the tasks with gymnasium

    return gym.make(task, **kwargs)


def _numpy(value: Any) -> np.ndarray:
    if hasattr(value, "detach"):  # a torch tensor, on the CPU or the GPU
        value = value.detach().cpu().numpy()
    return np.asarray(value)


def _flat(tree: Any) -> Any:
    """A dict of batched [N, ...] values, depth first in insertion order, as one float32 [N, n] tensor."""
    if isinstance(tree, Mapping):
        parts = [_flat(v) for v in tree.values()]
        return torch_cat(parts, None)
    value = _torch().as_tensor(tree).float()
    return value.reshape(value.shape[0], -1)


def _torch() -> Any:
    """torch, imported on first use: the preflight (this module, in the launcher) needs none."""
    import torch

    return torch


def torch_cat(parts: list[Any], n: int | None) -> Any:
    """``parts`` ([N, n_i] each) side by side; none: an [n, 0] tensor."""
    return _torch().cat(parts, dim=1) if parts else _torch().zeros((n or 1, 0))


def _bool(value: Any) -> bool:
    return bool(_numpy(value).reshape(-1)[0])


def _info(info: Mapping[str, Any]) -> dict[str, Any]:
    """ManiSkill's info with its one-element tensors as Python scalars (``success`` a bool); other values dropped."""
    out: dict[str, Any] = {}
    for key, value in info.items():
        array = _numpy(value)
        if array.size == 1 and array.dtype.kind in "biuf":
            out[key] = array.reshape(-1)[0].item()
    if "success" in out:
        out["success"] = bool(out["success"])
    return out


def check_kwargs(kwargs: Mapping[str, Any]) -> None:
    """Reject ``env.kwargs`` the adapter cannot use, naming the key."""
    obs = kwargs.get("obs", "state")
    if obs not in OBS_MODES:
        raise EnvError(f"ManiSkill obs = {obs!r}: expected one of {', '.join(map(repr, OBS_MODES))}")
    size = kwargs.get("image_size", DEFAULT_IMAGE_SIZE)
    if isinstance(size, bool) or not isinstance(size, int) or size <= 0:
        raise EnvError(f"ManiSkill image_size = {size!r}: expected a positive integer (pixels per side)")
    backend = kwargs.get("sim_backend")  # None: the default
    if backend is not None and not (backend in ("physx_cpu", "auto") or str(backend).startswith("physx_cuda")):
        raise EnvError(f"ManiSkill sim_backend = {backend!r}: expected one of {', '.join(map(repr, SIM_BACKENDS))} "
                       "(or \"physx_cuda:N\")")
    if "num_envs" in kwargs:
        raise EnvError("ManiSkill num_envs: the adapter runs one environment per worker process (or one "
                       "vectorized environment per group); set sim.envs_per_group instead")


# --- preflight --------------------------------------------------------------------------------


@dataclass(frozen=True)
class VulkanScan:
    """What the machine offers SAPIEN, read from device nodes and Vulkan driver manifests without loading Vulkan."""

    gpu: str | None  # the GPU found, described; None: no GPU
    nvidia: bool  # the GPU is NVIDIA's (SAPIEN renders on it through CUDA)
    software: tuple[str, ...]  # manifests of software drivers (lavapipe, ...), which SAPIEN may or may not accept
    summary: str  # what was looked at, for the error message


def mani_skill_installed() -> bool:
    return importlib.util.find_spec("mani_skill") is not None


def preflight(spec: EnvSpec, *, root: str | Path = "/", environ: Mapping[str, str] | None = None) -> None:
    """Raise :class:`EnvError` when ManiSkill cannot run here: no Vulkan device SAPIEN can render on, ManiSkill not
    installed, no CUDA torch for what ``spec`` asks of the GPU, or GPU PhysX without SAPIEN's GPU library and no
    way to download it (:func:`check_physx_gpu`). Reads files only (well under a second), except on a machine
    whose only Vulkan driver is a software one with ManiSkill installed: that costs a SAPIEN probe in a subprocess
    (1-2 s); and GPU PhysX without its library costs a check of the download host (2 s at most).
    ``root`` and ``environ`` are where the machine is read from (tests point them elsewhere);
    ``EBRL_MANISKILL_SKIP_PREFLIGHT=1`` skips the checks."""
    environ = os.environ if environ is None else environ
    if environ.get(SKIP_PREFLIGHT_VAR) == "1":
        return
    check_kwargs(spec.kwargs)
    where = f"env.id = {spec.id!r} (backend maniskill)"
    scan = scan_vulkan(root, environ)
    installed = mani_skill_installed()
    if scan.gpu is None:  # checked first: on a machine without a GPU, installing ManiSkill would not help
        # a software driver will do if SAPIEN accepts it, which only an installed SAPIEN can tell
        failure = probe_software_rendering(environ) if scan.software and installed else None
        if not (scan.software and installed and failure is None):
            tried = (f"; SAPIEN rejects the CPU driver ({failure}; Mesa 25's lavapipe works, 22.3's does not)"
                     if failure else "")
            raise EnvError(
                f"{where}: ManiSkill needs a Vulkan-capable GPU (an NVIDIA driver with its Vulkan ICD; SAPIEN renders "
                f"even for state observations), and none was found: {scan.summary}{tried}. On a CPU-only machine "
                f"use {', '.join(CPU_CONFIGS[:-1])} or {CPU_CONFIGS[-1]} instead ({SKIP_PREFLIGHT_VAR}=1 skips "
                "this check)")
        logging.getLogger(__name__).warning(
            "%s: no Vulkan GPU here; SAPIEN renders on the CPU (%s): fine for state observations, slow for cameras",
            where, ", ".join(Path(p).name for p in scan.software))
    if not installed:
        raise EnvError(f"{where}: ManiSkill is not installed; {MANISKILL.install}")
    need = _needs_cuda_torch(spec.kwargs, scan.nvidia)
    if need and not devices.cuda_available():
        raise EnvError(f"{where}: {need} needs torch with CUDA, and torch.cuda.is_available() is False here; "
                       "install a CUDA build of torch, or use obs = \"state\" with sim_backend = \"physx_cpu\"")
    check_physx_gpu(devices.physx_backend(spec.kwargs.get("sim_backend")), where, environ)


def _needs_cuda_torch(kwargs: Mapping[str, Any], nvidia: bool) -> str:
    """What in ``kwargs`` hands torch CUDA tensors (empty: nothing). Camera images rendered on a CUDA device (an
    NVIDIA GPU, ManiSkill's default render backend there) come back as CUDA tensors whatever the sim backend
    (ManiSkill's RenderCamera.get_picture)."""
    backend = str(kwargs.get("sim_backend") or "")
    if backend.startswith("physx_cuda"):
        return f"sim_backend = {backend!r}"
    render = str(kwargs.get("render_backend", "gpu"))  # ManiSkill's aliases; "sapien_cuda:N" picks GPU N
    if nvidia and kwargs.get("obs", "state") == "rgb" and render.split(":")[0] in ("gpu", "cuda", "sapien_cuda"):
        return f"obs = \"rgb\" rendered on the GPU (render_backend = {render!r})"
    return ""


def sapien_version() -> str:
    """The installed SAPIEN's release, read from its package metadata (no import); without SAPIEN, the pinned one."""
    try:
        return importlib.metadata.version("sapien")
    except importlib.metadata.PackageNotFoundError:
        return PHYSX_PINNED


def physx_gpu_library(environ: Mapping[str, str] | None = None) -> tuple[Path, str, str] | None:
    """Where SAPIEN looks for its GPU PhysX library, as sapien.physx.enable_gpu() computes it (sapien 3.0.3):
    ``Path.home() / ".sapien" / "physx" / <PhysX version> / "libPhysXGpu_64.so"``, with no variable to move it;
    and the PhysX version and the release URL it downloads the zip from where the file is missing. None for a
    SAPIEN release whose PhysX version is not known here (nothing is checked then); without SAPIEN, the pinned one."""
    environ = os.environ if environ is None else environ
    version = PHYSX_VERSIONS.get(sapien_version())
    if version is None:
        return None
    home = Path(environ["HOME"]) if environ.get("HOME") else Path.home()  # Path.home(): $HOME, else the user's entry
    archive = "linux-aarch64-so.zip" if platform.machine() in ("aarch64", "arm64") else "linux-so.zip"
    return home / ".sapien" / "physx" / version / PHYSX_GPU_LIB, version, PHYSX_URL.format(version=version, zip=archive)


def download_host(environ: Mapping[str, str] | None = None) -> tuple[str, int]:
    """The host SAPIEN's download (requests, which honours the proxy variables) connects to first: the HTTPS proxy
    where one is set and github.com is not excluded from it, else github.com:443."""
    environ = os.environ if environ is None else environ
    proxy = next((environ[k] for k in ("HTTPS_PROXY", "https_proxy", "ALL_PROXY", "all_proxy") if environ.get(k)), "")
    bypass = [h.strip().lstrip(".") for h in (environ.get("NO_PROXY") or environ.get("no_proxy") or "").split(",")]
    if proxy and not any(h == "*" or (h and ("." + PHYSX_HOST[0]).endswith("." + h)) for h in bypass):
        url = urllib.parse.urlsplit(proxy if "://" in proxy else "http://" + proxy)
        if url.hostname:
            return url.hostname, url.port or (443 if url.scheme == "https" else 80)
    return PHYSX_HOST


def host_reachable(host: str, port: int, timeout: float = PROBE_TIMEOUT,
                   connect: Callable[..., Any] = socket.create_connection) -> bool:
    """Whether a TCP connection to ``host:port`` opens within ``timeout`` seconds. The attempt runs in a daemon
    thread, so a name lookup that hangs (which the socket timeout does not bound) cannot hold the caller longer."""
    opened = threading.Event()

    def attempt() -> None:
        try:
            connect((host, port), timeout=timeout).close()
            opened.set()
        except OSError:
            pass

    thread = threading.Thread(target=attempt, name="ebrl-physx-probe", daemon=True)
    thread.start()
    thread.join(timeout)
    return opened.is_set()


def physx_host_reachable(environ: Mapping[str, str]) -> bool:
    """The reachability check :func:`check_physx_gpu` uses by default (tests replace it)."""
    return host_reachable(*download_host(environ))


def check_physx_gpu(sim_backend: str, where: str, environ: Mapping[str, str] | None = None,
                    reachable: Callable[[Mapping[str, str]], bool] | None = None) -> None:
    """Raise :class:`EnvError` when ``sim_backend`` (resolved: ``"physx_cuda"``, ``"physx_cuda:N"``) asks for GPU
    PhysX and SAPIEN's GPU library is neither where SAPIEN loads it from nor downloadable (the download host does
    not answer in 2 s; ``reachable`` replaces that check). SAPIEN would otherwise try the download in the worker
    and fail there with a network stack trace. Nothing happens where the file is there, or can be fetched (SAPIEN
    downloads it). The preflight calls it in the launcher, and ManiSkill's process before ``gym.make``."""
    if not sim_backend.startswith("physx_cuda"):
        return
    environ = os.environ if environ is None else environ
    found = physx_gpu_library(environ)
    if found is None:
        return
    library, version, url = found
    if library.exists():  # SAPIEN only checks that it exists, then loads it
        return
    if (reachable or physx_host_reachable)(environ):
        return
    host, port = download_host(environ)
    raise EnvError(
        f"{where}: sim_backend = {sim_backend!r} needs SAPIEN's GPU PhysX library, {PHYSX_GPU_LIB} (PhysX "
        f"{version}), which is not in {library.parent}/ and cannot be downloaded here ({host}:{port} does not "
        f"answer). Fetch {url} on a machine with network access and unzip it into {library.parent}/ (SAPIEN then "
        f"loads it, no download); or run GPU physics on MuJoCo Warp instead: {MJWARP_CONFIG}")


_PROBE = "import sapien; sapien.render.RenderSystem(sapien.Device('cpu'))"


def probe_software_rendering(environ: Mapping[str, str], timeout: float = 60.0) -> str | None:
    """Whether SAPIEN renders on a software Vulkan driver here, tried in a fresh interpreter (1-2 s): None if it
    does, else why not (SAPIEN's own error, e.g. 'Failed to find a supported physical device "cpu"')."""
    try:
        done = subprocess.run([sys.executable, "-c", _PROBE], env=dict(environ), capture_output=True, text=True,
                              timeout=timeout)
    except subprocess.TimeoutExpired:
        return f"the SAPIEN probe timed out after {timeout:.0f} s"
    if done.returncode == 0:
        return None
    lines = [line.strip() for line in done.stderr.splitlines() if line.strip()]
    errors = [line for line in lines if line.split(":")[0].endswith(("Error", "Exception"))]
    return (errors or lines or [f"exit status {done.returncode}"])[-1]


def scan_vulkan(root: str | Path = "/", environ: Mapping[str, str] | None = None) -> VulkanScan:
    """The Vulkan devices SAPIEN could render on: an NVIDIA GPU (a /dev/nvidiaN node and the driver's Vulkan ICD,
    or its libGLX_nvidia.so.0, for which SAPIEN supplies a manifest), another vendor's GPU (a /dev/dri render node
    and a hardware Vulkan driver), and software drivers (lavapipe, llvmpipe, SwiftShader), which are no GPU."""
    environ = os.environ if environ is None else environ
    root = Path(root)
    icds, where, overridden = _icd_manifests(root, environ)
    kinds = {path: _icd_kind(path) for path in icds}
    software = tuple(p for p, kind in kinds.items() if kind == "cpu")
    nvidia_nodes = sorted(p for p in glob.glob(str(root / "dev" / "nvidia*")) if Path(p).name[6:].isdigit())
    render_nodes = sorted(glob.glob(str(root / "dev" / "dri" / "renderD*")))
    nvidia_icds = [p for p, kind in kinds.items() if kind == "nvidia"]
    gpu_icds = [p for p, kind in kinds.items() if kind == "gpu"]
    if nvidia_nodes:
        node = "/dev/" + Path(nvidia_nodes[0]).name
        if nvidia_icds:
            return VulkanScan(f"NVIDIA GPU {node} with the Vulkan ICD {_shown(root, nvidia_icds[0])}", True,
                              software, "")
        if not overridden and _find_lib(root, environ, NVIDIA_LIB):
            return VulkanScan(f"NVIDIA GPU {node} ({NVIDIA_LIB}; SAPIEN supplies the ICD manifest)", True,
                              software, "")
    if render_nodes and gpu_icds:
        node = "/dev/dri/" + Path(render_nodes[0]).name
        return VulkanScan(f"GPU {node} with the Vulkan ICD {_shown(root, gpu_icds[0])}", False, software, "")
    seen = ", ".join(Path(p).name + (" (CPU)" if kinds[p] == "cpu" else "") for p in icds) or "none"
    if nvidia_nodes:
        devices = (f"/dev/{Path(nvidia_nodes[0]).name} is there but not the driver's Vulkan part "
                   f"(no nvidia ICD manifest, no {NVIDIA_LIB})")
    else:
        devices = "no NVIDIA device (/dev/nvidia[0-9]*)"
    dri = "no /dev/dri/renderD* node" if not render_nodes else "/dev/dri render node(s) but no GPU Vulkan driver"
    return VulkanScan(None, False, software, f"{devices}, {dri}; Vulkan ICDs in {where}: {seen}")


def _icd_manifests(root: Path, environ: Mapping[str, str]) -> tuple[list[str], str, bool]:
    """The driver manifests the Vulkan loader would read, where they came from, and whether an environment
    variable chose them (VK_DRIVER_FILES, or the older VK_ICD_FILENAMES, replace the search directories)."""
    chosen = environ.get("VK_DRIVER_FILES") or environ.get("VK_ICD_FILENAMES")
    if chosen:
        entries, where = chosen.split(os.pathsep), "VK_DRIVER_FILES/VK_ICD_FILENAMES"
    else:
        entries, where = [str(root / d) for d in ICD_DIRS], ", ".join("/" + d for d in ICD_DIRS)
    entries += [e for e in environ.get("VK_ADD_DRIVER_FILES", "").split(os.pathsep) if e]
    files: list[str] = []
    for entry in entries:
        if os.path.isdir(entry):
            files += sorted(glob.glob(os.path.join(entry, "*.json")))
        elif os.path.isfile(entry):
            files.append(entry)
    return files, where, bool(chosen)


def _icd_kind(path: str) -> str:
    """The driver's kind, from its manifest: nvidia, cpu (a software rasterizer) or gpu (another vendor's)."""
    try:
        with open(path) as fh:
            library = str(json.load(fh).get("ICD", {}).get("library_path", ""))
    except (OSError, ValueError, AttributeError):
        library = ""
    names = f"{Path(path).name} {Path(library).name}".lower()
    if "nvidia" in names:
        return "nvidia"
    if any(marker in names for marker in CPU_DRIVERS):
        return "cpu"
    return "gpu"


def _find_lib(root: Path, environ: Mapping[str, str], name: str) -> bool:
    dirs = [d for d in environ.get("LD_LIBRARY_PATH", "").split(os.pathsep) if d] + [str(root / d) for d in LIB_DIRS]
    return any(os.path.exists(os.path.join(d, name)) for d in dirs)


def _shown(root: Path, path: str) -> str:
    """``path`` as it is on the machine (without a test's root)."""
    try:
        return "/" + str(Path(path).relative_to(root))
    except ValueError:
        return path
