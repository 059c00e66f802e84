"""``"auto"`` for policy.dtype, gen.compile and gen.device (issue 35): the decision rule on measured numbers, the
launcher's side on a host without a GPU (nothing measured, nothing changes), the child process that measures
(run for real; here torch sees no CUDA, so it says so), and on a GPU the measurement itself."""

from __future__ import annotations

import pytest
import torch

from ebrl import autotune, config
from ebrl.autotune import Candidate

GPU32, GPU32G = Candidate("cuda", "float32", "off"), Candidate("cuda", "float32", "cudagraphs")
GPU16, GPU16G = Candidate("cuda", "bfloat16", "off"), Candidate("cuda", "bfloat16", "cudagraphs")
CPU = Candidate("cpu", "float32", "off")


def quickstart(*overrides: str):
    return config.load("configs/quickstart.toml", list(overrides))


def test_generation_and_training_on_one_gpu_add_up_and_the_cpu_runs_beside_it():
    cfg = quickstart()
    # training takes 10 us per decision in either precision: a GPU gen of 4 us costs 14 us of the GPU, a CPU
    # gen of 9 us runs beside it (10 us, the larger): the CPU wins
    d = autotune.decide(cfg, {GPU32: 4e-6, CPU: 9e-6}, {"float32": 10e-6}, train_on_gpu=True)
    assert d.settings == {"policy.dtype": "float32", "gen.compile": "off", "gen.device": "cpu"}
    assert d.costs == {str(GPU32): pytest.approx(14e-6), str(CPU): pytest.approx(10e-6)}
    # training on the CPU as well: the CPU gen's time is what it costs; the GPU's 4 us win
    d = autotune.decide(cfg, {GPU32: 4e-6, CPU: 9e-6}, {}, train_on_gpu=False)
    assert d.settings == {"policy.dtype": "float32", "gen.compile": "off", "gen.device": "auto"}
    assert "generation on the GPU float32 eager" in d.line and "250,000/s" in d.line


def test_the_fastest_wins_and_a_tie_goes_to_float32_eager_and_the_gpu():
    cfg = quickstart()
    gen = {GPU32: 10e-6, GPU32G: 4e-6, GPU16: 9e-6, GPU16G: 3.9e-6, CPU: 50e-6}
    d = autotune.decide(cfg, gen, {"float32": 1e-6, "bfloat16": 1e-6}, train_on_gpu=True)
    assert d.settings["gen.compile"] == "cudagraphs" and d.settings["policy.dtype"] == "float32"  # 5.0 vs 4.9: a tie
    d = autotune.decide(cfg, gen, {"float32": 8e-6, "bfloat16": 3e-6}, train_on_gpu=True)  # training decides
    assert (d.settings["policy.dtype"], d.settings["gen.compile"]) == ("bfloat16", "cudagraphs")


def test_explicit_values_narrow_the_candidates():
    assert autotune.candidates(quickstart(), gpu=True, bf16=True, train_on_gpu=True) == autotune.PREFERENCE
    assert autotune.candidates(quickstart(), gpu=False, bf16=True, train_on_gpu=True) == [CPU]
    assert autotune.candidates(quickstart(), gpu=True, bf16=False, train_on_gpu=True) == [GPU32, GPU32G, CPU]
    assert autotune.candidates(quickstart(), gpu=True, bf16=True, train_on_gpu=False) == [GPU32, GPU32G, CPU]
    assert autotune.candidates(quickstart('policy.dtype="bfloat16"', 'gen.device="cuda"'), gpu=True, bf16=True,
                               train_on_gpu=True) == [GPU16, GPU16G]
    assert autotune.candidates(quickstart('gen.compile="off"'), gpu=True, bf16=True, train_on_gpu=True) == [
        GPU32, GPU16, CPU]
    assert CPU not in autotune.candidates(quickstart('gen.compile="cudagraphs"'), gpu=True, bf16=True,
                                          train_on_gpu=True)  # the config refuses CUDA graphs on the CPU
    # only the fields left "auto" are set
    cfg = quickstart('gen.compile="off"')
    d = autotune.decide(cfg, {GPU32: 1e-6}, {}, train_on_gpu=True)
    assert d.settings == {"policy.dtype": "float32", "gen.device": "auto"}


def test_without_a_gpu_nothing_is_measured_and_nothing_changes(monkeypatch):
    monkeypatch.setattr(autotune, "run_child", lambda cfg: pytest.fail("measured on a host without a GPU"))
    cfg, d = autotune.settle(quickstart(), ("sim", "gen", "train"), multi=False)
    assert (cfg.policy.dtype, cfg.gen.compile, cfg.gen.device) == ("float32", "off", "auto")
    assert d.line == "auto: policy.dtype = 'float32', gen.compile = 'off' (no GPU on this host)"
    cfg, d = autotune.settle(quickstart('policy.dtype="float32"', 'gen.compile="off"'), ("gen",), multi=False)
    assert d.settings == {} and d.line == ""  # gen.device "auto": the GPU would be measured against the CPU
    assert autotune.settle(quickstart('policy.dtype="float32"', 'gen.compile="off"', 'gen.device="cpu"'), ("gen",),
                           multi=False)[1] is None  # nothing was "auto"
    cfg, d = autotune.settle(quickstart(), ("gen", "train"), multi=False,
                             earlier={"policy.dtype": "bfloat16", "gen.compile": "cudagraphs"})
    assert (cfg.policy.dtype, cfg.gen.compile) == ("bfloat16", "cudagraphs") and "as this run decided" in d.line
    # a run resumed where its start put generation on the GPU ("auto") measures nothing again
    cfg, d = autotune.settle(quickstart(), ("gen", "train"), multi=False,
                             earlier={"policy.dtype": "bfloat16", "gen.compile": "cudagraphs", "gen.device": "auto"})
    assert (cfg.policy.dtype, cfg.gen.compile, cfg.gen.device) == ("bfloat16", "cudagraphs", "auto")
    assert d.line.endswith("(as this run decided at its start)"), d.line
    cfg, d = autotune.settle(quickstart(), ("sim",), multi=True)  # several hosts: one precision for all
    assert cfg.policy.dtype == "float32"
    with pytest.raises(config.ConfigError, match="policy.dtype"):
        quickstart('policy.dtype="float16"')


def test_on_a_gpu_host_the_child_measures_and_says_what_it_found(monkeypatch):
    """The launcher's side where NVML finds a GPU (the one thing faked: there is none here): the child process
    runs for real, loads the config and, as torch sees no CUDA GPU in it, says so; the run gets float32, eager."""
    monkeypatch.setattr(autotune, "host_has_gpu", lambda: True)
    monkeypatch.setenv("EBRL_AUTOTUNE_CACHE", "off")
    cfg, d = autotune.settle(quickstart(), ("sim", "gen", "train"), multi=False)
    if torch.cuda.is_available():
        pytest.skip("a real GPU: test_the_measurement_on_a_gpu covers it")
    assert (cfg.policy.dtype, cfg.gen.compile) == ("float32", "off")
    assert d.line.endswith("(torch sees no CUDA GPU here)"), d.line


def test_the_whole_measurement_runs_with_the_cpu_standing_in_for_the_gpu():
    """Every line of the measurement but CUDA's own: the policy built from the config's task, each candidate's
    forward timed at the run's batch sizes (CUDA graphs: nothing to capture on the CPU, so no such candidate),
    training's step timed in both precisions, and a decision among them."""
    d = autotune.measure(quickstart(), accelerator="cpu")
    assert set(d.gen_s) == {str(GPU32), str(GPU16), str(CPU)}, d.gen_s
    assert set(d.train_s) == {"float32", "bfloat16"} and all(0 < v < 0.01 for v in [*d.gen_s.values(), *d.train_s.values()])
    assert set(d.settings) == {"policy.dtype", "gen.compile", "gen.device"} and d.settings["gen.compile"] == "off"
    assert d.costs[str(GPU32)] == pytest.approx(d.gen_s[str(GPU32)] + d.train_s["float32"])  # one device: they add up


@pytest.mark.gpu
@pytest.mark.skipif(not torch.cuda.is_available(), reason="needs a CUDA device (benchmarks/gpu/check.sh runs it on a "
                                                           "GPU machine)")
def test_the_measurement_on_a_gpu():
    """Every candidate timed (graphs captured), training timed in both precisions, a decision among them."""
    d = autotune.measure(quickstart())
    assert set(d.gen_s) >= {str(GPU32), str(GPU32G), str(CPU)}, d.gen_s
    assert all(0 < v < 1 for v in d.gen_s.values()) and set(d.train_s) >= {"float32"}
    assert d.settings["policy.dtype"] in ("float32", "bfloat16") and d.settings["gen.compile"] in ("off", "cudagraphs")
    assert d.line.startswith("auto: generation on the ")


def test_a_measured_decision_is_kept_for_the_next_run_of_the_same_config(monkeypatch, tmp_path):
    """What a GPU child would answer (the boundary faked: no GPU here) is kept in EBRL_AUTOTUNE_CACHE; the same
    config starts without measuring again, another batch size measures anew, "off" keeps nothing."""
    calls = []

    def child(cfg):
        calls.append(cfg.train.batch_size)
        return autotune.decide(cfg, {GPU32G: 2e-6, CPU: 9e-6}, {"float32": 1e-6}, train_on_gpu=True)

    monkeypatch.setattr(autotune, "host_has_gpu", lambda: True)
    monkeypatch.setattr(autotune, "run_child", child)
    monkeypatch.setenv("EBRL_AUTOTUNE_CACHE", str(tmp_path / "autotune.json"))
    cfg, first = autotune.settle(quickstart(), ("gen", "train"), multi=False)
    assert cfg.gen.compile == "cudagraphs" and calls == [1024] and "measured earlier" not in first.line
    cfg, again = autotune.settle(quickstart(), ("gen", "train"), multi=False)
    assert cfg.gen.compile == "cudagraphs" and calls == [1024] and "measured earlier on this machine" in again.line
    autotune.settle(quickstart("train.batch_size=512"), ("gen", "train"), multi=False)
    assert calls == [1024, 512]
    monkeypatch.setenv("EBRL_AUTOTUNE_CACHE", "off")
    autotune.settle(quickstart(), ("gen", "train"), multi=False)
    assert calls == [1024, 512, 1024]
    (tmp_path / "autotune.json").write_text("{not json")  # a broken file: measured again, rewritten
    monkeypatch.setenv("EBRL_AUTOTUNE_CACHE", str(tmp_path / "autotune.json"))
    autotune.settle(quickstart(), ("gen", "train"), multi=False)
    assert calls == [1024, 512, 1024, 1024] and autotune.cached(quickstart()) is not None


def test_bfloat16_asked_for_on_a_cpu_without_bfloat16_units_runs_float32_and_says_so(monkeypatch):
    from ebrl import devices

    monkeypatch.setattr(autotune, "host_has_gpu", lambda: False)
    monkeypatch.setattr(devices, "cpu_has_bf16", lambda: False)
    asked = quickstart('policy.dtype="bfloat16"', 'gen.compile="off"', 'gen.device="cpu"')
    cfg, d = autotune.settle(asked, ("sim", "gen", "train"), multi=False)
    assert cfg.policy.dtype == "float32" and d.settings == {"policy.dtype": "float32"}
    assert "no bfloat16 units" in d.line
    assert autotune.settle(asked, ("sim",), multi=False)[0].policy.dtype == "bfloat16"  # nothing of it runs here
    monkeypatch.setattr(devices, "cpu_has_bf16", lambda: True)  # AVX-512 BF16 or AMX: as asked
    assert autotune.settle(asked, ("gen", "train"), multi=False) == (asked, None)
