"""gen.device and train.device: resolution and config errors, the memory cap, one-transfer results; on a GPU
(``pytest -m gpu``, benchmarks/gpu/check.sh) the same policy and learner on CUDA.

Without CUDA the GPU is faked only at its boundary (``torch.cuda``'s queries and its memory-fraction call)."""

from __future__ import annotations

import subprocess
import sys
from pathlib import Path

import numpy as np
import pytest
import torch

from ebrl import config, devices
from ebrl.envs.obs import ObsLayout
from ebrl.policies import load_checkpoint, make_policy, save_checkpoint
from ebrl.policies.base import to_host

ROOT = Path(__file__).resolve().parent.parent
CUDA = torch.cuda.is_available()


def gpu_only(test):
    """A test that needs CUDA: marked ``gpu`` (``pytest -m gpu``) and skipped, saying why, elsewhere."""
    skip = pytest.mark.skipif(not CUDA, reason="needs a CUDA device (benchmarks/gpu/check.sh runs it on a GPU machine)")
    return pytest.mark.gpu(skip(test))


def test_device_settings_are_checked_by_name():
    cfg = config.from_dict({})
    assert (cfg.gen.device, cfg.train.device) == ("auto", "auto")
    for bad in ("gpu", "cuda:", "cuda:x", "CUDA"):
        with pytest.raises(config.ConfigError, match="train.device"):
            config.from_dict({"train": {"device": bad}})
    with pytest.raises(config.ConfigError, match="gen.device"):
        config.from_dict({"gen": {"device": "tpu"}})
    assert devices.resolve("cpu", "gen.device") == torch.device("cpu")


@pytest.mark.skipif(CUDA, reason="checks the refusal on a machine without CUDA")
def test_a_cuda_device_where_there_is_none_stops_ebrl_up_before_anything_starts(tmp_path):
    assert devices.resolve("auto", "train.device") == torch.device("cpu")
    proc = subprocess.run([sys.executable, "-m", "ebrl.cli", "up", str(ROOT / "configs" / "quickstart.toml"),
                           "--set", "train.device=cuda", "--set", f'run.output_dir="{tmp_path}"'],
                          capture_output=True, text=True, timeout=180, cwd=ROOT)
    assert proc.returncode == 2, proc.stderr
    assert "train.device = 'cuda'" in proc.stderr and "no CUDA device" in proc.stderr
    assert not list(tmp_path.iterdir())  # nothing started, no run directory


class FakeCuda:
    """``torch.cuda`` seen from EBRL's side on a machine with ``count`` GPUs of 80 GiB."""

    def __init__(self, monkeypatch, count: int = 1):
        self.fractions: list[tuple[float, torch.device]] = []
        props = type("Props", (), {"total_memory": 80 << 30, "name": "Fake H100"})()
        monkeypatch.setattr(torch.cuda, "is_available", lambda: True)
        monkeypatch.setattr(torch.cuda, "device_count", lambda: count)
        monkeypatch.setattr(torch.cuda, "current_device", lambda: 0)
        monkeypatch.setattr(torch.cuda, "get_device_properties", lambda device: props)
        monkeypatch.setattr(torch.cuda, "set_per_process_memory_fraction",
                            lambda fraction, device: self.fractions.append((fraction, device)))


def test_devices_resolve_against_what_torch_sees(monkeypatch):
    FakeCuda(monkeypatch, count=2)
    assert devices.resolve("auto", "gen.device") == torch.device("cuda", 0)
    assert devices.resolve("cuda:1", "gen.device") == torch.device("cuda", 1)
    with pytest.raises(devices.DeviceError, match=r"train.device = 'cuda:2': this process sees 2 CUDA"):
        devices.resolve("cuda:2", "train.device")
    # data-parallel ranks: one GPU each while there are enough, then they share
    assert [devices.rank_device("cuda", "train.device", r).index for r in range(3)] == [0, 1, 0]
    assert devices.rank_device("cuda:1", "train.device", 0).index == 1  # asked for by name: as it is


def test_a_memory_budget_becomes_the_processes_cuda_cap(monkeypatch):
    cuda = FakeCuda(monkeypatch)
    assert devices.parse_mps_limit("0=1024M") == 1 << 30
    assert devices.parse_mps_limit("1=2G,0=20G") == 20 << 30 and devices.parse_mps_limit("1=2G") is None
    device = torch.device("cuda", 0)
    assert devices.apply_memory_cap(device, 20 << 30) == pytest.approx(0.25)
    assert cuda.fractions == [(0.25, device)]
    monkeypatch.setenv(devices.MPS_MEM_VAR, "0=40G")
    assert devices.launch_memory_cap(device) == pytest.approx(0.5)
    assert devices.apply_memory_cap(torch.device("cpu"), 1 << 30) is None  # no cap on the CPU
    assert devices.apply_memory_cap(device, None) is None and len(cuda.fractions) == 2


def test_results_come_back_in_one_transfer_with_their_shapes():
    a, b, c = torch.randn(5, 4, 3), torch.randn(5), torch.zeros(5, 0)
    ha, hb, hc = to_host(a, b, c)
    assert ha.shape == (5, 4, 3) and hb.shape == (5,) and hc.shape == (5, 0)
    np.testing.assert_array_equal(ha, a.numpy())
    np.testing.assert_array_equal(hb, b.numpy())
    staged = devices.Staging(torch.device("cpu"))(np.ones((2, 3), np.float64))
    assert staged.dtype == torch.float32 and staged.shape == (2, 3)


def small_policy(kind: str, device: str = "cpu"):
    cfg = config.PolicySection(kind=kind, chunk=4, hidden=[32, 32], channels=[8], embed_dim=16, denoise_steps=3,
                               init_log_std=-0.5, normalize_obs=True, checkpoint="")
    torch.manual_seed(0)
    return make_policy(cfg, ObsLayout.vector(6), 2).to(device)


@gpu_only
@pytest.mark.parametrize("kind", ["mlp", "flow"])
def test_a_policy_on_the_gpu_evaluates_as_on_the_cpu_and_its_checkpoint_loads_on_the_cpu(tmp_path, kind):
    cpu, cuda = small_policy(kind), small_policy(kind, "cuda")
    obs = np.random.default_rng(0).normal(size=(16, 6)).astype(np.float32)
    cuda.obs_norm.merge(cuda.obs_norm.sums(torch.from_numpy(obs).cuda()))  # statistics from a GPU batch
    cpu.obs_norm.merge(cpu.obs_norm.sums(obs))
    actions, logprobs, values, latents = cuda.act(devices.Staging(torch.device("cuda"))(obs))
    assert actions.shape == (16, 4, 2) and np.isfinite(logprobs).all() and np.isfinite(values).all()
    args = [torch.from_numpy(x) for x in (obs, actions, latents)]
    lp_cpu, _, v_cpu = cpu.evaluate(*args)
    lp_gpu, _, v_gpu = cuda.evaluate(*(x.cuda() for x in args))
    torch.testing.assert_close(lp_gpu.cpu(), lp_cpu, rtol=1e-4, atol=1e-4)
    torch.testing.assert_close(v_gpu.cpu(), v_cpu, rtol=1e-4, atol=1e-4)
    path = str(tmp_path / "policy.safetensors")
    save_checkpoint(cuda, path, {"run": "gpu"})  # saved on the GPU ...
    back = small_policy(kind)
    load_checkpoint(back, path)  # ... resumed on the CPU
    torch.testing.assert_close(back.evaluate(*args)[0], lp_cpu, rtol=1e-4, atol=1e-4)


@gpu_only
def test_the_memory_cap_bites():
    device = torch.device("cuda", 0)
    assert devices.apply_memory_cap(device, 1 << 30) is not None  # 1 GiB for this process
    try:
        with pytest.raises(torch.OutOfMemoryError):
            torch.empty(2 << 30, dtype=torch.uint8, device=device)
        torch.empty(256 << 20, dtype=torch.uint8, device=device)  # under the cap: fine
    finally:
        torch.cuda.set_per_process_memory_fraction(1.0, device)


def test_cudagraphs_on_the_cpu_runs_eagerly_and_naming_the_cpu_is_refused():
    from ebrl.policies.graphs import Actor
    policy = small_policy("flow")
    actor = Actor(policy, "cudagraphs")
    assert not actor.graphed
    actions, logprobs, values, latents = actor(torch.randn(3, 6))
    assert actions.shape == (3, 4, 2) and latents.shape == (3, 4, 2) and not actor.graphs
    with pytest.raises(config.ConfigError, match="gen.compile = 'cudagraphs'.*gen.device is 'cpu'"):
        config.load("configs/quickstart.toml", ['gen.device="cpu"', 'gen.compile="cudagraphs"'])


@gpu_only
@pytest.mark.parametrize("kind", ["mlp", "flow"])
def test_cuda_graphs_sample_what_the_eager_policy_samples_and_follow_new_weights(kind):
    from ebrl.policies import load_arrays, state_arrays
    from ebrl.policies.graphs import MAX_GRAPHS, Actor
    policy = small_policy(kind, "cuda").eval()
    actor = Actor(policy, "cudagraphs")
    stage = devices.Staging(torch.device("cuda"))
    rng = np.random.default_rng(1)
    for round_ in range(3):
        for batch in (4, 12, 4):
            obs = rng.normal(size=(batch, 6)).astype(np.float32)
            actions, logprobs, values, latents = actor(stage(obs))
            assert actions.shape == (batch, 4, 2) and np.isfinite(actions).all()
            # the replayed graph computed this batch: its log-probs and values are the eager policy's
            lp, _, v = policy.evaluate(*(torch.from_numpy(x).cuda() for x in (obs, actions, latents)))
            torch.testing.assert_close(torch.from_numpy(logprobs), lp.cpu(), rtol=1e-4, atol=1e-3)
            torch.testing.assert_close(torch.from_numpy(values), v.cpu(), rtol=1e-4, atol=1e-4)
        assert sorted(actor.graphs) == [4, 12]
        # fresh noise on every replay: two replays of one batch differ
        a1, a2 = actor(stage(obs))[0], actor(stage(obs))[0]
        assert not np.allclose(a1, a2)
        # new weights, copied in place, are what the next replay uses
        fresh = small_policy(kind)
        with torch.no_grad():
            for p in fresh.parameters():
                p.add_(0.1 * (round_ + 1))
        load_arrays(policy, state_arrays(fresh))
    for batch in range(1, MAX_GRAPHS + 3):  # past MAX_GRAPHS sizes: eager, still right
        assert actor(stage(rng.normal(size=(batch, 6)).astype(np.float32)))[0].shape == (batch, 4, 2)
    assert len(actor.graphs) == MAX_GRAPHS
