"""Evaluation: confidence intervals, episodes in a plain gymnasium loop, videos, `ebrl eval`, the eval service's
choice of versions, its best policy and its worker processes."""

import dataclasses
import json
import math
import os
import subprocess
import sys
from pathlib import Path
from types import SimpleNamespace

import imageio
import numpy as np
import pytest
import torch

import ebrl
from ebrl import evaluate
from ebrl.config import Config, EnvSection, PolicySection, dump_toml
from ebrl.envs import EnvSpec, describe
from ebrl.evaluate import (BestPolicy, Episode, EvalPool, EvalResult, EvalSchedule, run_episodes, t_interval,
                           wilson_interval)
from ebrl.policies import make_policy, save_checkpoint, state_arrays
from ebrl.policies.checkpoint import policy_metadata, portable_metadata, read_metadata

ROOT = Path(__file__).resolve().parent.parent
TESTS = Path(__file__).resolve().parent
POLICY = PolicySection(kind="mlp", chunk=2, hidden=[8])
TOY = EnvSection(id="user_envs:SeedSuccess-v0")  # 5 steps; succeeds when the reset seed is even
PENDULUM = EnvSection(id="InvertedPendulum-v5")


def save(path, env: EnvSection = TOY, kind: str = "mlp", version: int = 7, seed: int = 0):
    torch.manual_seed(seed)
    cfg = dataclasses.replace(POLICY, kind=kind)
    info = describe(EnvSpec.from_config(env))
    model = make_policy(cfg, info.layout, info.action_dim)
    save_checkpoint(model, str(path), {"version": str(version), **portable_metadata(cfg, env, info)})
    return model


# --- intervals, by hand -------------------------------------------------------------------------------------------


def test_the_t_interval_of_the_mean_matches_hand_values():
    # mean 3, s = 1.58114, s / sqrt(5) = 0.70711, t(0.975, 4) = 2.77645: 3 -+ 1.96324
    mean, lo, hi = t_interval([1, 2, 3, 4, 5])
    assert mean == 3 and lo == pytest.approx(1.03676, abs=1e-4) and hi == pytest.approx(4.96324, abs=1e-4)
    mean, lo, hi = t_interval([10.0, 12.0])  # t(0.975, 1) = 12.7062, s / sqrt(2) = 1: 11 -+ 12.706
    assert (mean, lo, hi) == (11.0, pytest.approx(-1.7062, abs=1e-3), pytest.approx(23.7062, abs=1e-3))
    mean, lo, hi = t_interval([4.0])
    assert mean == 4.0 and math.isnan(lo) and math.isnan(hi)


def test_the_wilson_interval_matches_hand_values():
    # z = 1.95996; 8/10: centre (0.8 + z^2/20) / (1 + z^2/10) = 0.71678, half 0.22649
    assert wilson_interval(8, 10) == (0.8, pytest.approx(0.49016, abs=1e-4), pytest.approx(0.94331, abs=1e-4))
    assert wilson_interval(0, 10) == (0.0, 0.0, pytest.approx(0.27753, abs=1e-4))  # not [0, 0]: 10 tries say little
    assert wilson_interval(10, 10) == (1.0, pytest.approx(0.72247, abs=1e-4), 1.0)
    assert all(math.isnan(x) for x in wilson_interval(0, 0))


# --- episodes ------------------------------------------------------------------------------------------------------


def test_episodes_are_reproducible_and_report_success_with_its_interval(tmp_path):
    save(tmp_path / "p.safetensors")
    policy = ebrl.load_policy(tmp_path / "p.safetensors")
    result = run_episodes(policy, 4, seed=10)
    assert [e.seed for e in result.episodes] == [10, 11, 12, 13]
    assert [e.success for e in result.episodes] == [True, False, True, False]
    assert [(e.ret, e.length) for e in result.episodes] == [(5.0, 5)] * 4
    m = result.metrics()
    rate, lo, hi = wilson_interval(2, 4)
    assert (m["eval/success_rate"], m["eval/success_rate_lo"], m["eval/success_rate_hi"]) == (rate, lo, hi)
    assert m["eval/return"] == 5.0 and m["eval/episode_length"] == 5.0 and m["eval/version"] == 7.0
    assert m["eval/return_lo"] == m["eval/return_hi"] == 5.0  # no spread
    again = run_episodes(ebrl.load_policy(tmp_path / "p.safetensors"), 4, seed=10)
    assert [dataclasses.replace(e) for e in again.episodes] == result.episodes


def test_deterministic_and_seeded_stochastic_evaluations_repeat_exactly(tmp_path):
    save(tmp_path / "p.safetensors", env=PENDULUM, seed=3)
    returns = [run_episodes(ebrl.load_policy(tmp_path / "p.safetensors"), 3).returns for _ in range(2)]
    np.testing.assert_array_equal(*returns)
    sampled = [run_episodes(ebrl.load_policy(tmp_path / "p.safetensors", seed=s), 3, deterministic=False).returns
               for s in (0, 99)]  # the sampling is seeded by each episode's seed, not by the policy's
    np.testing.assert_array_equal(*sampled)
    assert run_episodes(ebrl.load_policy(tmp_path / "p.safetensors"), 3).summary()["success_rate"] is None


@pytest.mark.parametrize("fmt", ["mp4", "gif"])
def test_videos_of_the_first_episodes_can_be_read_back(tmp_path, fmt, monkeypatch):
    monkeypatch.setattr(evaluate, "video_format", lambda: fmt)  # gif: as where no ffmpeg encoder is installed
    save(tmp_path / "p.safetensors")
    result = run_episodes(ebrl.load_policy(tmp_path / "p.safetensors"), 3, video_dir=tmp_path / "v",
                          video_episodes=2)
    assert sorted(os.listdir(tmp_path / "v")) == [f"episode-0.{fmt}", f"episode-1.{fmt}"]
    assert [e.video for e in result.episodes] == [str(tmp_path / "v" / f"episode-{i}.{fmt}") for i in (0, 1)] + [None]
    frames = [f for f in imageio.get_reader(tmp_path / "v" / f"episode-1.{fmt}")]
    assert len(frames) == 6  # the reset and five steps
    assert abs(int(frames[-1][..., 0].mean()) - 200) <= 3  # the last frame's grey (lossy encoding)


def test_ebrl_eval_on_a_run_directory_prints_the_table_and_writes_eval_json_and_videos(tmp_path):
    run_dir = tmp_path / "run"
    run_dir.mkdir()
    save(run_dir / "policy.safetensors")
    (run_dir / "config.toml").write_text(dump_toml(dataclasses.replace(Config(), env=TOY)))
    out = subprocess.run([sys.executable, "-m", "ebrl.cli", "eval", str(run_dir), "--episodes", "6", "--seed", "4",
                          "--video", str(tmp_path / "videos"), "--video-episodes", "1"], capture_output=True,
                         text=True, timeout=120, env=_env(), cwd=tmp_path)
    assert out.returncode == 0, out.stderr
    assert "success rate" in out.stdout and "50.0%" in out.stdout and "Wilson; 3/6" in out.stdout
    report = json.loads((run_dir / "eval.json").read_text())
    assert report["episodes"] == 6 and report["seeds"] == [4, 5, 6, 7, 8, 9] and report["deterministic"] is True
    assert report["version"] == 7 and report["env"] == TOY.id
    assert report["success_rate"]["rate"] == 0.5 and report["return"]["mean"] == 5.0
    assert report["videos"] == [str(tmp_path / "videos" / "episode-0.mp4")]
    assert len([f for f in imageio.get_reader(report["videos"][0])]) == 6


def test_ebrl_eval_on_a_file_writes_eval_json_in_the_working_directory(tmp_path):
    save(tmp_path / "p.safetensors")
    out = subprocess.run([sys.executable, "-m", "ebrl.cli", "eval", str(tmp_path / "p.safetensors"), "--episodes",
                          "2", "--stochastic"], capture_output=True, text=True, timeout=120, env=_env(), cwd=tmp_path)
    assert out.returncode == 0, out.stderr
    assert json.loads((tmp_path / "eval.json").read_text())["deterministic"] is False
    missing = subprocess.run([sys.executable, "-m", "ebrl.cli", "eval", str(tmp_path / "absent")], capture_output=True,
                             text=True, timeout=120, env=_env(), cwd=tmp_path)
    assert missing.returncode == 2 and "no such file or directory" in missing.stderr


def _env() -> dict[str, str]:
    return dict(os.environ, PYTHONPATH=os.pathsep.join([str(ROOT), str(TESTS)]))


# --- the eval service's parts ------------------------------------------------------------------------------------


def test_the_schedule_takes_every_nth_and_the_final_version_and_keeps_only_the_newest_waiting():
    schedule = EvalSchedule(every=10, final=25)
    v = lambda n: SimpleNamespace(version=n)  # noqa: E731
    assert [n for n in (0, 5, 10, 20, 25, 30) if schedule.due(n)] == [10, 20, 25, 30]
    assert not schedule.offer(v(5)) and schedule.take() is None
    assert schedule.offer(v(10)) and schedule.take().version == 10  # evaluation of v10 starts
    assert schedule.offer(v(20)) and schedule.offer(v(25))  # both arrive while it runs: v20 is dropped
    assert schedule.skipped == 1 and schedule.take().version == 25 and schedule.take() is None
    assert not schedule.offer(v(20))  # older than what was evaluated


def _result(version: int, successes: list[bool], ret: float) -> EvalResult:
    return EvalResult([Episode(i, ret, 5, s) for i, s in enumerate(successes)], True, version=version)


def test_the_best_policy_ranks_by_success_then_return_and_survives_a_restart(tmp_path):
    model = save(tmp_path / "p.safetensors")
    metadata = read_metadata(str(tmp_path / "p.safetensors"))
    best = BestPolicy(tmp_path / "best.safetensors")
    for version, successes, ret, better in [(10, [True, False], 5.0, True), (20, [False, False], 9.0, False),
                                            (30, [True, False], 6.0, True), (40, [True, True], 1.0, True),
                                            (50, [True, True], 0.5, False)]:
        result = _result(version, successes, ret)
        assert best.better(result) is better, version
        if better:
            best.save(model, metadata, result)
    os.umask(0o022)
    assert oct(os.stat(tmp_path / "best.safetensors").st_mode & 0o777) == "0o644"
    again = BestPolicy(tmp_path / "best.safetensors")  # the eval service started again
    assert (again.score, again.version) == ((1.0, 1.0), 40)
    assert not again.better(_result(60, [True, True], 0.9)) and again.better(_result(60, [True, True], 2.0))
    loaded = ebrl.load_policy(tmp_path / "best.safetensors")
    assert loaded.version == 40 and loaded.metadata["eval_success_rate"] == "1.0"


def test_worker_processes_evaluate_like_the_library_loop(tmp_path):
    model = save(tmp_path / "p.safetensors", env=PENDULUM, seed=5)
    info = describe(EnvSpec.from_config(PENDULUM))
    metadata = {**policy_metadata(model), **portable_metadata(POLICY, PENDULUM, info)}
    pool = EvalPool(metadata, cores=[0], render=True)
    try:
        result = pool.evaluate(state_arrays(model), 7, 3, 100, True, str(tmp_path / "videos"), 1)
        torch.manual_seed(1)
        with torch.no_grad():
            for p in model.parameters():
                p.add_(torch.randn_like(p) * 0.3)
        other = pool.evaluate(state_arrays(model), 8, 3, 100, True)  # the same worker, the next version's weights
    finally:
        pool.close()
    expected = run_episodes(ebrl.load_policy(tmp_path / "p.safetensors"), 3, seed=100)
    assert [e.ret for e in result.episodes] == [e.ret for e in expected.episodes]
    assert result.version == 7 and result.episodes[0].video.endswith("episode-0.mp4") and result.episodes[1].video is None
    assert len([f for f in imageio.get_reader(result.episodes[0].video)]) == result.episodes[0].length + 1
    assert [e.ret for e in other.episodes] != [e.ret for e in result.episodes]


def test_the_launcher_waits_for_the_final_evaluation_only_while_it_can_come(monkeypatch):
    from ebrl import launch
    from ebrl.messages import StatsReport
    from ebrl.runview import RunView
    from ebrl.supervisor import Child

    def result(version: float) -> tuple:
        return "ebrl/stats/r/eval/0", StatsReport(run="r", service="eval", instance=0, time=0.0, seq=0,
                                                  metrics={"eval/version": version, "eval/return": 1.0})

    said, now = [], [100.0]
    monkeypatch.setattr(launch.time, "monotonic", lambda: now[0])
    view, evaluator = RunView("r", iterations=4), Child("eval", 0, None, Path("eval-0.log"))
    wait = launch.FinalEvaluation(60.0, 4, said.append)
    assert wait.pending(view, [evaluator]) and "waiting for the evaluation of the final policy v4" in said[0]
    view.on_report(*result(2.0))
    view.on_report("ebrl/stats/r/eval/0", StatsReport(run="r", service="eval", instance=0, time=0.0, seq=1,
                                                      metrics={"eval/busy": 1.0}))  # a periodic report
    assert wait.pending(view, [evaluator]) and view.evaluated_version() == 2 and "eval v2" in view.progress_line(1.0)
    view.on_report(*result(4.0))
    assert not wait.pending(view, [evaluator])
    assert not launch.FinalEvaluation(60.0, 5, said.append).pending(view, [])  # no eval service on this host
    assert not launch.FinalEvaluation(60.0, 5, said.append).pending(view, [Child("eval", 0, None, Path("e.log"),
                                                                                   given_up=True)])
    shared = Child("train", 0, None, Path("p.log"), members=(("train", 0), ("eval", 0)))  # a process of several
    assert launch.FinalEvaluation(60.0, 5, said.append).pending(view, [shared])
    assert not launch.FinalEvaluation(0.0, 5, said.append).pending(view, [evaluator])
    late = launch.FinalEvaluation(60.0, 5, said.append)
    assert late.pending(view, [evaluator])
    now[0] += 61
    assert not late.pending(view, [evaluator]) and "no evaluation of v5 after 60 s" in said[-1]


def test_the_eval_section_is_checked_and_turns_the_service_on():
    from ebrl.config import ConfigError, describe as describe_keys, from_dict
    from ebrl.hosts import enabled_roles, plan

    cfg = from_dict({"eval": {"every": 5}})
    assert (cfg.eval.seeds, cfg.eval.deterministic, cfg.eval.episodes) == (2_000_000_000, True, 10)
    assert "eval" in enabled_roles(cfg) and "eval" not in enabled_roles(from_dict({}))
    assert "eval" in plan(cfg, only="train")[1].roles and "eval" not in plan(cfg, only="sim", instance=1)[1].roles
    with pytest.raises(ConfigError, match="did you mean eval.episodes"):
        from_dict({"eval": {"episode": 3}})
    with pytest.raises(ConfigError, match="eval.seeds"):
        from_dict({"eval": {"seeds": 2**32}})
    with pytest.raises(ConfigError, match=r"\[eval\]"):
        from_dict({"eval": {"every": -1}})
    listing = describe_keys()
    assert all(f"  {key} (" in listing.split("[eval]")[1] for key in ("every", "episodes", "seeds", "deterministic",
                                                                      "video_episodes", "cores", "final_timeout"))


def test_an_episode_cut_short_leaves_no_video(tmp_path):
    save(tmp_path / "p.safetensors")
    policy = ebrl.load_policy(tmp_path / "p.safetensors")
    calls = []

    def failing(obs, state=None, episode_start=None, deterministic=True):
        calls.append(1)
        if len(calls) == 3:
            raise RuntimeError("the simulator broke")
        return np.zeros(1, np.float32), None

    policy.predict = failing
    with pytest.raises(RuntimeError, match="simulator broke"):
        run_episodes(policy, 2, video_dir=tmp_path / "v", video_episodes=2)
    assert os.listdir(tmp_path / "v") == []
