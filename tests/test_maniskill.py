"""ManiSkill adapter: the preflight check (deterministic on any machine: it reads a fake root), the adapter against
a fake ManiSkill at its boundary (gym.make), and real PickCube-v1 episodes where SAPIEN can render."""

import asyncio
import json
import threading
import time
from pathlib import Path

import gymnasium as gym
import numpy as np
import pytest
import torch

from ebrl import config, devices
from ebrl.envs import EnvSpec, EnvWorker, tokenize
from ebrl.envs import maniskill
from ebrl.envs import EnvError
from ebrl.envs.maniskill import (CPU_CONFIGS, INSTRUCTIONS, MJWARP_CONFIG, ManiSkillEnv, download_host, host_reachable,
                                 preflight, scan_vulkan)

REPO = Path(__file__).resolve().parent.parent
SPEC = EnvSpec("PickCube-v1", backend="maniskill")


def machine(root: Path, *, nvidia: bool = False, nvidia_icd: bool = False, glx: bool = False, dri: bool = False,
            icds: tuple[str, ...] = ("lvp_icd.x86_64.json", "intel_icd.x86_64.json")) -> Path:
    """A fake filesystem root: device nodes, Vulkan driver manifests, the NVIDIA GL library."""
    (root / "dev").mkdir(parents=True)
    if nvidia:
        for name in ("nvidia0", "nvidiactl", "nvidia-uvm"):
            (root / "dev" / name).touch()
    if dri:
        (root / "dev" / "dri").mkdir()
        (root / "dev" / "dri" / "renderD128").touch()
    libraries = {"lvp_icd.x86_64.json": "libvulkan_lvp.so", "intel_icd.x86_64.json": "libvulkan_intel.so",
                 "nvidia_icd.json": "libGLX_nvidia.so.0", "radeon_icd.x86_64.json": "libvulkan_radeon.so"}
    icd_dir = root / "usr" / "share" / "vulkan" / "icd.d"
    icd_dir.mkdir(parents=True)
    for name in icds + (("nvidia_icd.json",) if nvidia_icd else ()):
        manifest = {"file_format_version": "1.0.0", "ICD": {"library_path": libraries[name], "api_version": "1.3"}}
        (icd_dir / name).write_text(json.dumps(manifest))
    if glx:
        lib = root / "usr" / "lib" / "x86_64-linux-gnu"
        lib.mkdir(parents=True)
        (lib / "libGLX_nvidia.so.0").touch()
    return root


@pytest.fixture
def installed(monkeypatch):
    """ManiSkill counts as installed, SAPIEN's CPU-driver probe is never run for real, torch has no CUDA."""
    monkeypatch.setattr(maniskill, "mani_skill_installed", lambda: True)
    monkeypatch.setattr(maniskill, "probe_software_rendering", lambda environ: "RuntimeError: probe not faked")
    monkeypatch.setattr(devices, "cuda_available", lambda: False)


# --- preflight --------------------------------------------------------------------------------


def test_preflight_without_a_gpu_says_so_in_one_line_and_names_the_cpu_configs(tmp_path, monkeypatch):
    monkeypatch.setattr(maniskill, "mani_skill_installed", lambda: False)
    root = machine(tmp_path)  # as on the CI machines: Mesa's drivers installed, lavapipe among them, no GPU
    with pytest.raises(EnvError) as err:
        preflight(SPEC, root=root, environ={})
    message = str(err.value)
    assert "\n" not in message and "PickCube-v1" in message and "Vulkan-capable GPU" in message
    assert all(cfg in message for cfg in CPU_CONFIGS)
    assert "lvp_icd.x86_64.json (CPU)" in message and "no NVIDIA device" in message
    assert "EBRL_MANISKILL_SKIP_PREFLIGHT=1" in message


def test_preflight_lavapipe_is_no_gpu_unless_sapien_renders_on_it(tmp_path, monkeypatch, installed):
    root = machine(tmp_path)
    assert scan_vulkan(root, {}).gpu is None and scan_vulkan(root, {}).software
    rejected = 'RuntimeError: Failed to find a supported physical device "cpu"'
    monkeypatch.setattr(maniskill, "probe_software_rendering", lambda environ: rejected)
    with pytest.raises(EnvError, match="Vulkan-capable GPU") as err:
        preflight(SPEC, root=root, environ={})
    assert rejected in str(err.value) and CPU_CONFIGS[0] in str(err.value)
    monkeypatch.setattr(maniskill, "probe_software_rendering", lambda environ: None)  # e.g. Mesa 25's lavapipe
    preflight(SPEC, root=root, environ={})


def test_preflight_with_a_gpu_but_without_mani_skill_says_how_to_install(tmp_path, monkeypatch):
    monkeypatch.setattr(maniskill, "mani_skill_installed", lambda: False)
    with pytest.raises(EnvError, match=r"pip install -e '\.\[maniskill\]'"):
        preflight(SPEC, root=machine(tmp_path, nvidia=True, nvidia_icd=True), environ={})


def test_preflight_passes_with_an_nvidia_gpu_and_its_vulkan_driver(tmp_path, installed):
    root = machine(tmp_path, nvidia=True, nvidia_icd=True)
    scan = scan_vulkan(root, {})
    assert scan.nvidia
    assert scan.gpu == "NVIDIA GPU /dev/nvidia0 with the Vulkan ICD /usr/share/vulkan/icd.d/nvidia_icd.json"
    preflight(EnvSpec("PickCube-v1", backend="maniskill", kwargs={"obs": "state", "sim_backend": "physx_cpu"}),
              root=root, environ={})


def test_nvidia_device_needs_the_drivers_vulkan_part(tmp_path):
    root = machine(tmp_path / "bare", nvidia=True)
    assert scan_vulkan(root, {}).gpu is None and "/dev/nvidia0 is there" in scan_vulkan(root, {}).summary
    root = machine(tmp_path / "glx", nvidia=True, glx=True)  # no manifest: SAPIEN supplies one for libGLX_nvidia
    assert scan_vulkan(root, {}).nvidia
    only_lavapipe = {"VK_ICD_FILENAMES": str(root / "usr/share/vulkan/icd.d/lvp_icd.x86_64.json")}
    assert scan_vulkan(root, only_lavapipe).gpu is None  # the loader is told to see lavapipe only


def test_another_vendors_gpu_counts_but_a_render_node_for_lavapipe_does_not(tmp_path):
    scan = scan_vulkan(machine(tmp_path / "amd", dri=True, icds=("lvp_icd.x86_64.json", "radeon_icd.x86_64.json")), {})
    assert scan.gpu == "GPU /dev/dri/renderD128 with the Vulkan ICD /usr/share/vulkan/icd.d/radeon_icd.x86_64.json"
    assert not scan.nvidia
    assert scan_vulkan(machine(tmp_path / "soft", dri=True, icds=("lvp_icd.x86_64.json",)), {}).gpu is None


def test_preflight_asks_for_cuda_torch_where_the_gpu_hands_over_cuda_tensors(tmp_path, installed):
    root = machine(tmp_path, nvidia=True, nvidia_icd=True)
    for kwargs in ({"sim_backend": "physx_cuda"}, {"obs": "rgb", "sim_backend": "physx_cpu"}):
        with pytest.raises(EnvError, match="needs torch with CUDA"):
            preflight(EnvSpec("PickCube-v1", backend="maniskill", kwargs=kwargs), root=root, environ={})
    preflight(EnvSpec("PickCube-v1", backend="maniskill", kwargs={"obs": "rgb", "render_backend": "cpu"}),
              root=root, environ={})


def test_preflight_rejects_bad_kwargs_and_can_be_skipped(tmp_path, installed):
    root = machine(tmp_path, nvidia=True, nvidia_icd=True)
    for kwargs, key in (({"obs": "depth"}, "obs"), ({"sim_backend": "gpu"}, "sim_backend"),
                        ({"image_size": 0}, "image_size"), ({"num_envs": 4}, "num_envs")):
        with pytest.raises(EnvError, match=key):
            preflight(EnvSpec("PickCube-v1", backend="maniskill", kwargs=kwargs), root=root, environ={})
    preflight(SPEC, root=tmp_path / "nothing", environ={"EBRL_MANISKILL_SKIP_PREFLIGHT": "1"})


def test_preflight_never_hangs_here():
    """Without a GPU the preflight answers (an EnvError) instead of waiting on a Vulkan device; well under a
    second itself, so the generous bound is for a fresh interpreter on a loaded machine, not a timing test."""
    import subprocess
    import sys

    code = ("from ebrl.envs.maniskill import preflight; from ebrl.envs.spec import EnvSpec, EnvError\n"
            "try: preflight(EnvSpec('PickCube-v1', backend='maniskill'))\nexcept EnvError: pass")
    subprocess.run([sys.executable, "-c", code], check=True, timeout=120)


PHYSX = "105.1-physx-5.3.1.patch0"  # sapien 3.0.3's sapien.physx.version()
PHYSX_ZIP = f"https://github.com/sapien-sim/physx-precompiled/releases/download/{PHYSX}/linux-so.zip"


@pytest.fixture
def gpu_physx(tmp_path, monkeypatch, installed):
    """A machine that passes every check before SAPIEN's GPU library: an NVIDIA GPU with its Vulkan driver, CUDA
    torch, SAPIEN 3.0.3; a home of its own, without the library; the download host unreachable (tests change it)."""
    monkeypatch.setattr(devices, "cuda_available", lambda: True)
    monkeypatch.setattr(maniskill, "sapien_version", lambda: "3.0.3")
    monkeypatch.setattr(maniskill, "physx_host_reachable", lambda environ: False)
    monkeypatch.setattr(maniskill.platform, "machine", lambda: "x86_64")
    home = tmp_path / "home"
    home.mkdir()
    return machine(tmp_path / "root", nvidia=True, nvidia_icd=True), {"HOME": str(home)}, home


def test_gpu_physx_offline_without_sapiens_library_says_what_to_copy_where(gpu_physx):
    """Offline, SAPIEN's first-use download of libPhysXGpu_64.so would fail in a worker with a network stack
    trace; the preflight says at once which file, from where, into which folder, and the MuJoCo Warp config."""
    root, environ, home = gpu_physx
    folder = f"{home}/.sapien/physx/{PHYSX}/"
    for backend in ("physx_cuda", "physx_cuda:1", "auto"):  # auto: physx_cuda, torch sees a GPU
        spec = EnvSpec("PickCube-v1", backend="maniskill", kwargs={"sim_backend": backend})
        start = time.monotonic()
        with pytest.raises(EnvError) as err:
            preflight(spec, root=root, environ=environ)
        assert time.monotonic() - start < 5.0
        message = str(err.value)
        assert "\n" not in message and "PickCube-v1" in message
        assert f"libPhysXGpu_64.so (PhysX {PHYSX})" in message and f"unzip it into {folder}" in message
        assert PHYSX_ZIP in message and "github.com:443" in message
        assert MJWARP_CONFIG == "configs/mjwarp_pickcube.toml" and MJWARP_CONFIG in message
        assert (REPO / MJWARP_CONFIG).is_file()  # the config the message sends a user to is there


def test_gpu_physx_passes_with_sapiens_library_or_a_reachable_download_host(gpu_physx, monkeypatch):
    """Where the library is in SAPIEN's folder nothing is probed (SAPIEN loads it); where it is missing but the
    download host answers, SAPIEN downloads it as before; under CPU PhysX the library is not needed."""
    root, environ, home = gpu_physx
    spec = EnvSpec("PickCube-v1", backend="maniskill", kwargs={"sim_backend": "physx_cuda"})
    preflight(EnvSpec("PickCube-v1", backend="maniskill", kwargs={"sim_backend": "physx_cpu"}), root=root,
              environ=environ)
    library = home / ".sapien" / "physx" / PHYSX / "libPhysXGpu_64.so"
    library.parent.mkdir(parents=True)
    library.touch()

    def no_probe(environ):
        raise AssertionError("the download host is probed although the library is there")

    monkeypatch.setattr(maniskill, "physx_host_reachable", no_probe)
    preflight(spec, root=root, environ=environ)
    library.unlink()
    monkeypatch.setattr(maniskill, "physx_host_reachable", lambda environ: True)
    preflight(spec, root=root, environ=environ)


def test_gpu_physx_is_checked_again_in_the_batch_process(gpu_physx, monkeypatch):
    """A run that skipped the preflight gets the same error from ManiSkill's own process, before gym.make (the
    check comes before ManiSkill is imported, which is not installed here)."""
    from ebrl.envs.batch import ManiSkillBatch

    _, environ, home = gpu_physx
    monkeypatch.setenv("HOME", environ["HOME"])
    spec = EnvSpec("PickCube-v1", backend="maniskill", kwargs={"sim_backend": "physx_cuda"})
    start = time.monotonic()
    with pytest.raises(EnvError, match=r"libPhysXGpu_64\.so") as err:
        ManiSkillBatch(spec, 4, seed=0)
    assert time.monotonic() - start < 5.0
    assert f"{home}/.sapien/physx/{PHYSX}/" in str(err.value) and MJWARP_CONFIG in str(err.value)


def test_download_host_probe_is_bounded_and_follows_the_proxy():
    """The probe answers within its timeout even when the connection (or the name lookup before it) hangs; it
    asks the HTTPS proxy where SAPIEN's download (requests) would go through one."""
    release = threading.Event()

    def hangs(address, timeout):
        release.wait(30)
        raise OSError("released")

    start = time.monotonic()
    try:
        assert host_reachable("github.com", 443, timeout=0.2, connect=hangs) is False
        assert time.monotonic() - start < 2.0
    finally:
        release.set()

    class Socket:
        def close(self):
            pass

    def refused(address, timeout):
        raise ConnectionRefusedError(address)

    assert host_reachable("github.com", 443, connect=lambda address, timeout: Socket()) is True
    assert host_reachable("github.com", 443, connect=refused) is False
    assert download_host({}) == ("github.com", 443)
    assert download_host({"https_proxy": "http://proxy.lab:3128"}) == ("proxy.lab", 3128)
    assert download_host({"HTTPS_PROXY": "proxy.lab:3128", "NO_PROXY": "localhost,.github.com"}) == ("github.com", 443)


def test_config_parses():
    cfg = config.load(str(REPO / "configs" / "maniskill.toml"))
    assert cfg.env.backend == "maniskill" and cfg.env.id == "PickCube-v1"
    assert cfg.env.kwargs["obs"] == "state" and cfg.policy.kind == "mlp"


# --- the adapter against a fake ManiSkill -------------------------------------------------------


class FakeManiSkill(gym.Env):
    """What ``gym.make("PickCube-v1", num_envs=1, ...)`` returns, as ManiSkill 3.0.1 builds it: batched torch
    tensors ([1, ...]), a dict observation with cameras in "rgb" mode, one-element tensors in info."""

    made: dict = {}

    def __init__(self, **kwargs):
        FakeManiSkill.made = kwargs
        self.obs_mode = kwargs["obs_mode"]
        self.limit = kwargs.get("max_episode_steps", 50)
        self.single_action_space = gym.spaces.Box(-1.0, 1.0, (8,), np.float32)
        self.t = 0

    def _obs(self):
        if self.obs_mode == "state":
            return torch.full((1, 42), float(self.t))
        size = self.made["sensor_configs"]["width"]
        image = torch.zeros((1, size, size, 3), dtype=torch.uint8)
        image[..., 0] = 255  # all red
        return dict(agent=dict(qpos=torch.ones(1, 9), qvel=torch.zeros(1, 9)),
                    extra=dict(is_grasped=torch.tensor([True]), tcp_pose=torch.ones(1, 7),
                               goal_pos=torch.full((1, 3), 2.0)),
                    sensor_param=dict(base_camera=dict(intrinsic_cv=torch.eye(3)[None])),
                    sensor_data=dict(base_camera=dict(rgb=image)))

    def _info(self):
        return dict(elapsed_steps=torch.tensor([self.t], dtype=torch.int32), success=torch.tensor([self.t >= 2]),
                    is_grasped=torch.tensor([False]))

    def reset(self, *, seed=None, options=None):
        self.t = 0
        return self._obs(), dict(self._info(), reconfigure=False)

    def step(self, action):
        assert action.shape == (8,) and action.dtype == np.float32
        self.t += 1
        success = self._info()["success"]
        return (self._obs(), torch.tensor([0.25]), success.clone(), torch.tensor([self.t >= self.limit]),
                self._info())


@pytest.fixture
def fake(monkeypatch):
    monkeypatch.setattr(maniskill, "_make_maniskill", lambda task, **kwargs: FakeManiSkill(**kwargs))
    monkeypatch.setattr(devices, "cuda_available", lambda: False)


def test_state_observations_are_one_flat_float32_vector(fake):
    env = ManiSkillEnv("PickCube-v1", max_episode_steps=5)
    made = FakeManiSkill.made
    assert made["num_envs"] == 1 and made["obs_mode"] == "state" and made["reward_mode"] == "normalized_dense"
    assert made["sim_backend"] == "physx_cpu" and made["control_mode"] == "pd_joint_delta_pos"
    assert made["max_episode_steps"] == 5 and "sensor_configs" not in made
    assert env.obs_layout.describe() == "state:vector[42]" and env.observation_space.shape == (42,)
    assert env.action_space.shape == (8,) and env.action_space.dtype == np.float32
    assert env.instruction == INSTRUCTIONS["PickCube-v1"]
    obs, info = env.reset(seed=1)
    assert obs.dtype == np.float32 and obs.shape == (42,) and info["success"] is False
    obs, reward, terminated, truncated, info = env.step(np.zeros(8))
    assert obs[0] == 1.0 and type(reward) is float and reward == 0.25
    assert terminated is False and truncated is False
    assert info == {"elapsed_steps": 1, "success": False, "is_grasped": False}
    _, _, terminated, _, info = env.step(np.zeros(8))
    assert terminated is True and info["success"] is True  # ManiSkill ends an episode on success


def test_rgb_observations_carry_image_proprio_and_instruction(fake):
    env = ManiSkillEnv("PushCube-v1", obs="rgb", image_size=16, sim_backend="physx_cpu",
                       sensor_configs={"shader_pack": "minimal"})
    assert FakeManiSkill.made["obs_mode"] == "rgb"
    assert FakeManiSkill.made["sensor_configs"] == {"width": 16, "height": 16, "shader_pack": "minimal"}
    assert env.obs_layout.describe() == "image:image[3, 16, 16] + proprio:vector[29] + instruction:tokens[16]"
    obs, _ = env.reset()
    parts = {name: part[0] for name, part in env.obs_layout.split(obs[None]).items()}
    assert np.all(parts["image"][0] == 1.0) and np.all(parts["image"][1:] == 0.0)  # channel-first, in [0, 1]
    assert parts["proprio"][:9].tolist() == [1.0] * 9 and parts["proprio"][18] == 1.0  # qpos ... is_grasped
    assert parts["proprio"][-3:].tolist() == [2.0] * 3  # the goal, which the camera does not show
    assert np.array_equal(parts["instruction"], tokenize(INSTRUCTIONS["PushCube-v1"]))


def test_instruction_override_and_tokens_in_state_mode(fake):
    env = ManiSkillEnv("PickCube-v1", instruction="lift it", instruction_tokens=True)
    assert env.instruction == "lift it" and env.obs_layout.describe() == "state:vector[42] + instruction:tokens[16]"
    obs, _ = env.reset()
    assert np.array_equal(obs[42:], tokenize("lift it"))


# --- real ManiSkill (where SAPIEN can render: a GPU, or a CPU Vulkan driver it accepts) ---------


def _why_not_here(**kwargs) -> str:
    try:
        preflight(EnvSpec("PickCube-v1", backend="maniskill", kwargs=kwargs))
    except EnvError as exc:
        return str(exc)
    return ""


NOT_HERE = _why_not_here(sim_backend="physx_cpu")


@pytest.mark.skipif(bool(NOT_HERE), reason=NOT_HERE)
def test_pickcube_steps_resets_and_reports_success():
    env = ManiSkillEnv("PickCube-v1", max_episode_steps=4, sim_backend="physx_cpu")
    try:
        assert env.action_space.shape == (8,) and env.obs_layout.describe() == "state:vector[42]"
        first, _ = env.reset(seed=7)
        again, _ = env.reset(seed=7)
        assert first.dtype == np.float32 and np.array_equal(first, again)  # a seed fixes the episode
        for t in range(4):
            obs, reward, terminated, truncated, info = env.step(env.action_space.sample())
            assert obs.shape == (42,) and type(reward) is float and 0.0 <= reward <= 1.0
            assert type(info["success"]) is bool and type(terminated) is bool and type(truncated) is bool
        assert truncated  # the time limit ends the episode
    finally:
        env.close()


NOT_HERE_RGB = _why_not_here(obs="rgb", sim_backend="physx_cpu")


@pytest.mark.skipif(bool(NOT_HERE_RGB), reason=NOT_HERE_RGB)
def test_pickcube_camera_observations():
    env = ManiSkillEnv("PickCube-v1", obs="rgb", image_size=32, sim_backend="physx_cpu")
    try:
        obs, _ = env.reset(seed=0)
        image = env.obs_layout.split(obs[None])["image"][0]
        assert image.shape == (3, 32, 32) and 0.0 <= image.min() < image.max() <= 1.0
        assert env.obs_layout.split(obs[None])["proprio"].shape == (1, 29)
    finally:
        env.close()


@pytest.mark.skipif(bool(NOT_HERE), reason=NOT_HERE)
def test_pickcube_in_a_worker_process():
    async def scenario():
        spec = EnvSpec("PickCube-v1", backend="maniskill", max_episode_steps=6, kwargs={"sim_backend": "physx_cpu"})
        worker = EnvWorker(spec, seed=3)
        try:
            obs = await worker.reset()
            assert obs.shape == (42,) and obs.dtype == np.float32
            result = await worker.chunk(np.zeros((4, 8), np.float32))
            assert result.steps == 4 and not result.truncated
            result = await worker.chunk(np.zeros((4, 8), np.float32))
            assert result.truncated and result.steps == 2 and result.episode_length == 6
            assert result.episode_success is False
        finally:
            worker.close()

    asyncio.run(scenario())
