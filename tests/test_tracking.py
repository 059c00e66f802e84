"""Tracking: the log service on a real bus writes TensorBoard events and CSV rows keyed by env steps; per-episode
records; non-finite values dropped; a failing sink is closed while the others go on; W&B offline; meta.json."""

from __future__ import annotations

import asyncio
import csv
import glob
import json
import math
import os
import struct
import subprocess
import sys
import time
from pathlib import Path

import numpy as np
import pytest

import helpers
from ebrl import config, meta, tracking
from ebrl import keys
from ebrl.messages import EpisodeBatch, StatsReport, Stop
from ebrl.tracking import Point, Tracker

ROOT = helpers.ROOT
RUN = "trk"


def report(service: str, instance: int, seq: int, metrics: dict[str, float], at: float | None = None) -> StatsReport:
    return StatsReport(run=RUN, service=service, instance=instance, time=at or time.time(), seq=seq, metrics=metrics)


def episodes(instance: int, returns: list[float], steps: list[int], success: list[bool | None]) -> EpisodeBatch:
    n = len(returns)
    return EpisodeBatch(service="sim", instance=instance, env_id=list(range(n)), episode=[0] * n, returns=returns,
                        length=[10] * n, success=success, policy_version=[1] * n, env_steps=steps,
                        end_time=[time.time()] * n)


class ListSink:
    """A sink that keeps what it is given (and can be told to fail)."""

    def __init__(self, name: str = "list", fail: bool = False):
        self.name, self.fail = name, fail
        self.points: list[Point] = []
        self.closed = False

    def scalars(self, points):
        if self.fail:
            raise OSError("disk full")
        self.points += points

    def flush(self):
        pass

    def close(self):
        self.closed = True

    def series(self, key: str) -> list[tuple[int, float]]:
        return [(p.step, p.value) for p in self.points if p.key == key]


# --- the tracker's logic ---------------------------------------------------------------------------


def test_steps_are_the_runs_env_steps_over_every_simulator_and_survive_a_restart():
    sink = ListSink()
    tracker = Tracker([sink])
    tracker.on_messages([report("sim", 0, 0, {"sim/env_steps": 100.0}), report("sim", 1, 0, {"sim/env_steps": 50.0})])
    assert tracker.env_steps == 150
    tracker.on_messages([report("train", 0, 0, {"train/policy_loss": 0.5, "train/policy_version": 3.0,
                                                "proc/rss_mb": 300.0}), report("gen", 0, 0, {"proc/rss_mb": 200.0})])
    assert sink.series("train/policy_loss") == [(150, 0.5)]
    # what every service reports goes under the service: no two services share a tag
    assert sink.series("train/proc/rss_mb") == [(150, 300.0)] and sink.series("gen/proc/rss_mb") == [(150, 200.0)]
    tracker.on_messages([report("sim", 1, 1, {"sim/env_steps": 10.0})])  # sim/1 restarted: its counter began again
    assert tracker.env_steps == 100 + 50 + 10
    assert sink.series("sim/env_steps/1") == [(150, 50.0), (160, 10.0)]  # instance 1 has its own tag
    assert [s for s, _ in sink.series("run/env_steps")] == [100]  # written with sim/0's reports
    # episodes of sim/1 ended at its counts 4 and 9 (after the restart): the run had 100 + 50 + that
    tracker.on_messages([episodes(1, [1.0, 2.0], [4, 9], [True, None])])
    assert sink.series("episode/return/1") == [(154, 1.0), (159, 2.0)]
    assert sink.series("episode/success/1") == [(154, 1.0)]  # a task without a success check writes none
    assert Tracker([ListSink()], env_steps_before=1000).env_steps == 1000  # a resumed run goes on


def test_an_eval_result_sits_at_the_env_steps_its_policy_version_was_published():
    sink = ListSink()
    tracker = Tracker([sink])
    tracker.on_messages([report("sim", 0, 0, {"sim/env_steps": 1000.0}), report("train", 0, 0, {"train/policy_version": 5.0})])
    tracker.on_messages([report("sim", 0, 1, {"sim/env_steps": 3000.0}), report("train", 0, 1, {"train/policy_version": 6.0})])
    tracker.on_messages([report("eval", 0, 0, {"eval/version": 5.0, "eval/success_rate": 0.4, "eval/return": 12.0})])
    assert sink.series("eval/success_rate") == [(1000, 0.4)] and sink.series("eval/return") == [(1000, 12.0)]
    tracker.on_messages([report("eval", 0, 1, {"eval/version": 99.0, "eval/success_rate": 0.5})])  # unknown version
    assert sink.series("eval/success_rate")[-1] == (3000, 0.5)  # at the current env steps


def test_non_finite_values_are_dropped_and_counted_and_exclusions_apply():
    sink = ListSink()
    tracker = Tracker([sink], exclude=["cpu/*"])
    tracker.on_messages([report("train", 0, 0, {"train/approx_kl": math.nan, "train/entropy": math.inf,
                                                "train/value_loss": 0.25, "cpu/core0_percent": 50.0})])
    assert [p.key for p in sink.points] == ["train/value_loss"]
    assert tracker.nonfinite_dropped == 2 and tracker.metrics()["log/nonfinite_dropped"] == 2.0
    tracker.on_messages([episodes(0, [math.nan, 3.0], [1, 2], [False, True])])
    assert sink.series("episode/return") == [(2, 3.0)] and sink.series("episode/success") == [(1, 0.0), (2, 1.0)]


def test_a_sink_that_keeps_failing_is_closed_and_the_others_go_on():
    good, bad = ListSink("good"), ListSink("bad", fail=True)
    tracker = Tracker([bad, good])
    for seq in range(tracking.SINK_FAILURES_MAX + 3):
        tracker.on_messages([report("train", 0, seq, {"train/value_loss": float(seq)})])
    assert len(good.series("train/value_loss")) == tracking.SINK_FAILURES_MAX + 3
    assert bad.closed and tracker.closed_sinks == ["bad"] and tracker.sink_errors == tracking.SINK_FAILURES_MAX
    assert [s.name for s in tracker.sinks] == ["good"]


def test_the_config_as_hyperparameters_is_flat_and_typed():
    cfg = config.load(str(ROOT / "configs" / "quickstart.toml"), ['env.kwargs={"obs.kind" = "rgb", size = 3}'])
    flat = tracking.flat_config(cfg)
    assert flat["run.seed"] == cfg.run.seed and flat["env.kwargs.obs.kind"] == "rgb" and flat["env.kwargs.size"] == 3
    assert flat["policy.hidden"] == "[64, 64]" and flat["log.tensorboard"] == "true"
    assert all(isinstance(v, (str, int, float)) for v in flat.values())


# --- the log service on a real bus -------------------------------------------------------------------


def write_run(tmp_path: Path, *sets: str) -> tuple[Path, config.Config]:
    run_dir = tmp_path / "run"
    (run_dir / "logs").mkdir(parents=True)
    # an open bus: the test's own publisher stands in for the run's services (bus.auth: tests/test_auth.py)
    cfg = config.load(str(ROOT / "configs" / "quickstart.toml"), [f'run.name="{RUN}"', "run.stats_interval=0.5",
                                                                 "bus.auth=false", *sets])
    (run_dir / "config.toml").write_text(config.dump_toml(cfg))
    meta.write(cfg, run_dir)
    return run_dir, cfg


async def feed_log_service(run_dir: Path, messages: list[tuple[str, object]]) -> tuple[int, str]:
    """Start ``python -m ebrl.services.log`` on the run in ``run_dir`` (its own process, a real Zenoh session),
    publish ``messages`` once it is live, stop it over the bus; its exit status and log."""
    port = helpers.free_port()
    bus = helpers.loopback_bus(port)
    live: set[str] = set()
    bus.watch_liveliness(keys.live(RUN, "log", 0), lambda key, alive: live.add(key) if alive else live.discard(key))
    log_path = run_dir / "logs" / "log-0.log"
    env = dict(os.environ, PYTHONPATH=str(ROOT) + os.pathsep + os.environ.get("PYTHONPATH", ""))
    with open(log_path, "ab") as out:
        proc = subprocess.Popen([sys.executable, "-m", "ebrl.services.log", "--config", str(run_dir / "config.toml"),
                                 "--connect", f"tcp/127.0.0.1:{port}"], stdout=out, stderr=subprocess.STDOUT, env=env)
    try:
        await helpers.until(lambda: live or proc.poll() is not None, 120, "the log service live")
        assert proc.poll() is None, log_path.read_text()
        for key, msg in messages:
            await bus.put(key, msg)
        await asyncio.sleep(1.5)  # written within WRITE_S; the stop must not race the samples
        await bus.put(keys.ctl(RUN, "log", 0, "stop"), Stop(reason="test over"))
        code = await asyncio.get_running_loop().run_in_executor(None, proc.wait, 60)
    finally:
        if proc.poll() is None:
            proc.kill()
        await bus.close()
    return code, log_path.read_text()


def run_messages(t0: float) -> list[tuple[str, object]]:
    """A small run's worth of stats: sim steps, training losses (one NaN), episodes, two eval versions."""
    out: list[tuple[str, object]] = []
    for i in range(4):
        out.append((keys.stats(RUN, "sim", 0), report("sim", 0, i, {"sim/env_steps": 1000.0 * (i + 1),
                                                                    "sim/episode_return_mean": 10.0 * i}, t0 + i)))
        out.append((keys.stats(RUN, "train", 0), report("train", 0, i, {
            "train/policy_version": float(i + 1), "train/policy_loss": -0.1 * i, "train/value_loss": 1.0 / (i + 1),
            "train/approx_kl": math.nan if i == 2 else 0.01 * i, "train/entropy": 1.5, "train/clipfrac": 0.1,
            "train/staleness_mean": 0.5}, t0 + i)))
        out.append((keys.episodes(RUN, "sim"), episodes(0, [float(i), float(i) + 0.5], [1000 * i + 10, 1000 * i + 20],
                                                        [i % 2 == 0, True])))
    for version, success in ((2, 0.25), (4, 0.75)):
        out.append((keys.stats(RUN, "eval", 0), report("eval", 0, version, {
            "eval/version": float(version), "eval/return": 100.0 * success, "eval/success_rate": success,
            "eval/success_rate_lo": success - 0.1, "eval/success_rate_hi": success + 0.1,
            "eval/episode_length": 50.0}, t0 + 5)))
    return out


def test_the_log_service_writes_tensorboard_and_csv_from_reports_on_the_bus(tmp_path):
    from tensorboard.backend.event_processing.event_accumulator import EventAccumulator

    run_dir, cfg = write_run(tmp_path)
    code, log_text = asyncio.run(feed_log_service(run_dir, run_messages(time.time())))
    assert code == 0, log_text
    assert "sinks: tensorboard, csv" in log_text

    acc = EventAccumulator(str(run_dir / tracking.TB_DIR))
    acc.Reload()
    scalars = set(acc.Tags()["scalars"])
    assert {"episode/return", "episode/success", "episode/length", "eval/success_rate", "eval/return",
            "train/policy_loss", "train/value_loss", "train/approx_kl", "train/entropy", "train/clipfrac",
            "train/staleness_mean", "sim/episode_return_mean", "run/env_steps"} <= scalars
    returns = [(e.step, e.value) for e in acc.Scalars("episode/return")]
    assert returns == [(1000 * i + 10 * k, float(i) + 0.5 * (k - 1)) for i in range(4) for k in (1, 2)]
    # each eval result at the env steps its version was published (train's report of version v came with sim's
    # report of 1000 v env steps)
    assert [(e.step, e.value) for e in acc.Scalars("eval/success_rate")] == [(2000, 0.25), (4000, 0.75)]
    assert [e.step for e in acc.Scalars("train/approx_kl")] == [1000, 2000, 4000]  # the NaN is not there
    assert {"config", "meta"} <= set(acc.PluginTagToContent("text"))  # the text plugin's records
    texts = {t: acc.Tensors(t)[0].tensor_proto.string_val[0].decode() for t in ("config", "meta")}
    assert f'name = "{RUN}"' in texts["config"] and "[log]" in texts["config"]
    assert '"ebrl_version"' in texts["meta"] and '"packages"' in texts["meta"]
    hparams = acc.PluginTagToContent("hparams")
    assert hparams, "no hparams"  # the experiment and the session's start (the config's values)
    assert any(b"run.seed" in content for content in hparams.values())

    with open(run_dir / tracking.CSV_FILE) as fh:
        rows = list(csv.DictReader(fh))
    assert list(rows[0]) == list(tracking.CSV_HEADER)
    episode_rows = [(int(r["step"]), float(r["value"])) for r in rows if r["key"] == "episode/return"]
    assert episode_rows == returns
    assert not [r for r in rows if not math.isfinite(float(r["value"]))]
    kl = [int(r["step"]) for r in rows if r["key"] == "train/approx_kl"]
    assert kl == [1000, 2000, 4000]


def test_a_log_service_with_every_sink_off_but_wandb_offline_writes_a_wandb_run(tmp_path):
    pytest.importorskip("wandb")
    run_dir, cfg = write_run(tmp_path, "log.tensorboard=false", "log.csv=false", "log.wandb=true",
                             'log.wandb_mode="offline"', 'log.wandb_project="ebrl-test"', 'log.wandb_tags=["a b"]')
    code, log_text = asyncio.run(feed_log_service(run_dir, run_messages(time.time())))
    assert code == 0, log_text
    assert "sinks: wandb" in log_text
    assert not (run_dir / tracking.TB_DIR).exists() and not (run_dir / tracking.CSV_FILE).exists()
    (path,) = glob.glob(str(run_dir / tracking.WANDB_DIR / "offline-run-*" / "run-*.wandb"))
    history, config_seen = [], ""
    for record in wandb_records(path):
        kind = record.WhichOneof("record_type")
        if kind == "history":
            history.append({"/".join(i.nested_key) or i.key: json.loads(i.value_json) for i in record.history.item})
        elif kind == "run":
            config_seen = str(record.run.config)
    returns = [(row["env_steps"], row["episode/return"]) for row in history if "episode/return" in row]
    assert returns == [(1000 * i + 10 * k, float(i) + 0.5 * (k - 1)) for i in range(4) for k in (1, 2)]
    eval_rows = [(row["env_steps"], row["eval/success_rate"]) for row in history if "eval/success_rate" in row]
    assert eval_rows == [(2000, 0.25), (4000, 0.75)]
    assert not any("train/approx_kl" in row and row["train/approx_kl"] is None for row in history)
    assert "ebrl_version" in config_seen and "wandb_project" in config_seen  # the config and meta.json


def wandb_records(path: str):
    """The records of a ``.wandb`` file: W&B's LevelDB-log framing (32 KiB blocks, 7-byte record headers) around
    its ``Record`` protobufs (the Python reader left the wandb package with 0.19)."""
    from wandb.proto import wandb_internal_pb2

    data = Path(path).read_bytes()
    ident, magic, _ = struct.unpack("<4sHB", data[:7])
    assert ident == b":W&B" and magic == 0xBEE1
    pos, parts, block = 7, b"", 32768
    while pos + 7 <= len(data):
        left = block - pos % block
        if left < 7:
            pos += left
            continue
        _, length, kind = struct.unpack("<IHB", data[pos:pos + 7])
        if kind == 0:  # padding to the end of the block
            pos += left
            continue
        chunk, pos = data[pos + 7:pos + 7 + length], pos + 7 + length
        parts = chunk if kind in (1, 2) else parts + chunk  # full, first | middle, last
        if kind in (1, 4):
            record = wandb_internal_pb2.Record()
            record.ParseFromString(parts)
            yield record


def test_wandb_problems_are_found_before_the_run_starts(tmp_path, monkeypatch):
    section = config.LogSection(wandb=True, wandb_mode="online")
    import importlib.util

    real = importlib.util.find_spec
    monkeypatch.setattr(importlib.util, "find_spec", lambda name, *a: None if name == "wandb" else real(name, *a))
    assert "pip install 'ebrl[wandb]'" in tracking.wandb_problem(section)
    with pytest.raises(tracking.WandbMissing, match=r"pip install 'ebrl\[wandb\]'"):
        monkeypatch.setitem(sys.modules, "wandb", None)  # import wandb raises ImportError
        tracking.import_wandb()
    monkeypatch.undo()
    if importlib.util.find_spec("wandb") is None:
        return
    monkeypatch.delenv("WANDB_API_KEY", raising=False)
    (tmp_path / "netrc").write_text("machine example.org login a password b\n")
    monkeypatch.setenv("NETRC", str(tmp_path / "netrc"))
    assert "wandb login" in tracking.wandb_problem(section)
    assert tracking.wandb_problem(config.LogSection(wandb=True, wandb_mode="offline")) is None
    monkeypatch.setenv("WANDB_API_KEY", "x" * 40)
    assert tracking.wandb_problem(section) is None
    assert tracking.wandb_problem(config.LogSection(wandb=False)) is None


# --- meta.json -----------------------------------------------------------------------------------------


def test_meta_json_says_code_packages_machine_seeds_and_command(tmp_path):
    import torch

    cfg = config.load(str(ROOT / "configs" / "quickstart.toml"), ["run.seed=7"])
    path = meta.write(cfg, tmp_path, argv=["ebrl", "up", "configs/quickstart.toml"])
    data = json.loads(path.read_text())
    import ebrl

    assert data["ebrl_version"] == ebrl.__version__ and data["run"] == cfg.run.name
    assert data["packages"]["torch"] == torch.__version__ and data["packages"]["numpy"] == np.__version__
    for name in ("gymnasium", "mujoco", "eclipse-zenoh", "tensorboard"):
        assert data["packages"][name], name
    assert data["python"] == sys.version.split()[0]
    m = data["machine"]
    assert m["cpu_count"] == os.cpu_count() and m["memory_gib"] > 0 and m["hostname"] and m["cpu_model"]
    assert isinstance(m["gpus"], list)
    assert data["seeds"]["run"] == 7 and data["seeds"]["gen"]["0"] == meta.gen_seed(7, 0) and data["seeds"]["train"] == 7
    assert data["command"] == ["ebrl", "up", "configs/quickstart.toml"] and data["started_at"].endswith("+00:00")
    head = subprocess.run(["git", "-C", str(ROOT), "rev-parse", "HEAD"], capture_output=True, text=True)
    if head.returncode == 0:  # in a checkout
        assert data["git"]["commit"] == head.stdout.strip()
    again = json.loads(meta.write(cfg, tmp_path, extra={"env_steps_before": 123}).read_text())
    assert again["started_at"] == data["started_at"] and again["resumed"][0]["env_steps_before"] == 123


def test_git_state_tells_clean_from_dirty(tmp_path):
    repo = tmp_path / "repo"
    repo.mkdir()

    def git(*args):
        subprocess.run(["git", "-C", str(repo), "-c", "user.email=t@t", "-c", "user.name=t", *args], check=True,
                       capture_output=True)

    git("init", "-q")
    (repo / "a.py").write_text("x = 1\n")
    git("add", "a.py")
    git("commit", "-qm", "one")
    state = meta.git_state(repo)
    assert state["dirty"] is False and len(state["commit"]) == 40
    (repo / "a.py").write_text("x = 2\n")
    assert meta.git_state(repo)["dirty"] is True
    assert meta.git_state(tmp_path / "nowhere") is None


def test_generation_samples_from_a_seed_fixed_per_instance():
    """gen/<i> seeds torch from run.seed and its instance: the same config and weights give the same actions, and
    two instances (or two seeds) differ."""
    import torch

    from ebrl.bus.memory import MemoryBus, MemoryNetwork
    from ebrl.policies import load_arrays
    from ebrl.services.gen import GenService

    cfg = config.load(str(ROOT / "configs" / "quickstart.toml"), ["run.seed=3"])
    obs = np.random.default_rng(0).standard_normal((8, 4)).astype(np.float32)
    params = None

    async def actions(instance: int, seed_cfg=cfg) -> np.ndarray:
        nonlocal params
        service = GenService(seed_cfg, instance)
        service.bus = MemoryBus(MemoryNetwork())
        try:
            await service.setup()
            if params is None:
                params = {k: v.detach().clone().numpy() for k, v in service.policy.state_dict().items()}
            load_arrays(service.policy, params)
            with torch.no_grad():
                return np.concatenate([service.forward(obs)[0] for _ in range(3)])
        finally:
            service.pool.shutdown()
            await service.bus.close()

    first, again, other = asyncio.run(actions(0)), asyncio.run(actions(0)), asyncio.run(actions(1))
    reseeded = asyncio.run(actions(0, config.load(str(ROOT / "configs" / "quickstart.toml"), ["run.seed=4"])))
    assert np.array_equal(first, again)
    assert not np.allclose(first, other) and not np.allclose(first, reseeded)


def test_the_log_service_writes_tensorboard_without_importing_torch(tmp_path):
    """The log service starts beside gen and train, which import torch: on a small host the CPU a third import
    took was time the first env step waited for. Its TensorBoard records come from TensorBoard's own writer."""
    run_dir, cfg = write_run(tmp_path)
    script = f"""
import sys
from pathlib import Path
import ebrl.services.log
from ebrl import config, tracking
cfg = config.load({str(run_dir / "config.toml")!r})
info = tracking.RunInfo(cfg.run.name, Path({str(run_dir)!r}), cfg, config.dump_toml(cfg), {{}})
sink = tracking.TensorBoardSink(info, 1.0)
sink.scalars([tracking.Point("run/env_steps", 3.0, 100, 1.0)])
sink.close()
print("torch imported" if "torch" in sys.modules else "no torch")
"""
    env = dict(os.environ, PYTHONPATH=str(ROOT) + os.pathsep + os.environ.get("PYTHONPATH", ""))
    out = subprocess.run([sys.executable, "-c", script], capture_output=True, text=True, env=env, cwd=ROOT,
                         timeout=120)
    assert out.returncode == 0, out.stderr
    assert out.stdout.strip() == "no torch"
    from tensorboard.backend.event_processing.event_accumulator import EventAccumulator

    acc = EventAccumulator(str(run_dir / tracking.TB_DIR))
    acc.Reload()
    assert [(e.step, e.value) for e in acc.Scalars("run/env_steps")] == [(100, 3.0)]
    from tensorboard.plugins.hparams.plugin_data_pb2 import HParamsPluginData

    start = HParamsPluginData.FromString(acc.PluginTagToContent("hparams")["_hparams_/session_start_info"])
    assert start.session_start_info.hparams["run.seed"].number_value == cfg.run.seed
    assert start.session_start_info.hparams["policy.kind"].string_value == "mlp"
