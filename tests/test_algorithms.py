"""The algorithm interface (``ebrl.algos.algorithm``): the registry, a user's own algorithm by ``module:Class``
trained by a real ``ebrl up``, and SAC behind the learner every algorithm shares: its update-to-data ratio, its
checkpoints, its replay service (restarted after a kill -9 with its contents, or what it lost counted), its policy
loaded and evaluated as a PPO one."""

from __future__ import annotations

import secrets
import subprocess
import sys
from pathlib import Path

import numpy as np
import pytest
import torch

import ebrl
from ebrl.algos.algorithm import Optimizers, algorithm_class
from ebrl.algos.learner import Learner
from ebrl.algos.offpolicy import SACAlgorithm
from ebrl.algos.replay import REPLAY_FILE, ReplayStore
from ebrl.algos.replaylink import make_request, minibatches
from ebrl.config import ConfigError, load
from ebrl.envs import EnvSpec, describe
from ebrl.messages import TrajectorySegment
from helpers import Counts, StatsWatcher, up
from test_metrics import assert_catalogued

TESTS = Path(__file__).resolve().parent
SMALL = ("policy.hidden=[32, 32]", "replay.batch_size=32", "replay.learning_starts=100")


def sac_config(*overrides: str):
    return load("sac_pendulum", list(SMALL) + list(overrides))


INFO = describe(EnvSpec.from_config(sac_config().env))  # Pendulum-v1: 3 observation values, 1 action in [-2, 2]


class DirectReplay:
    """A learner's link to a replay store in this thread: the calls of ``ebrl.algos.replaylink.ReplayLink``
    without the bus between (the real runs below take the bus)."""

    def __init__(self, store: ReplayStore):
        self.store, self.acked, self.closed = store, 0, False
        self.seq, self.session = 0, secrets.randbits(62)  # a process's own, as ReplayLink's

    def send(self, rows, batches: int, batch_size: int):
        self.seq += 1
        return make_request(self.session, self.seq, self.acked, rows, batches, batch_size, 3, 1), None

    def wait(self, request, _answer):
        sample = self.store.exchange(request)
        self.acked = sample.inserted
        return minibatches(sample)

    def close(self) -> None:
        self.closed = True


def sac_learner(run_dir, *overrides: str, store: ReplayStore | None = None) -> tuple[Learner, Counts]:
    telemetry = Counts()
    learner = Learner(sac_config(*overrides), INFO, 1, telemetry, str(run_dir))
    learner.algo.connect(DirectReplay(store or ReplayStore(3, 1, 10_000, seed=0)))
    return learner, telemetry


def pendulum_segments(n: int, length: int = 16, seed: int = 0, version: int = 0) -> list[TrajectorySegment]:
    """``n`` segments as a Pendulum simulator sends them: observations of cos, sin and velocity, actions within
    the bounds, rewards within the task's range."""
    rng = np.random.default_rng(seed)
    out = []
    for i in range(n):
        obs = rng.uniform(-1, 1, (length, 3)).astype(np.float32)
        out.append(TrajectorySegment(
            group=0, env_id=i % 4, episode=i, obs=obs, actions=rng.uniform(-2, 2, (length, 1, 1)).astype(np.float32),
            latents=np.zeros((length, 0), np.float32), logprobs=np.zeros(length, np.float32),
            values=np.zeros(length, np.float32), rewards=-rng.uniform(0, 10, length).astype(np.float32),
            steps=np.ones(length, np.int32), versions=np.full(length, version, np.int64), end="cut",
            last_obs=rng.uniform(-1, 1, 3).astype(np.float32), episode_returns=[], episode_lengths=[]))
    return out


def feed(learner: Learner, segments: list[TrajectorySegment]) -> list[dict[str, float]]:
    """Every segment in, then an update for each full batch, as the train service's cycle does."""
    for seg in segments:
        assert learner.accept(seg, lambda exc: pytest.fail(str(exc))) == 1
    out = []
    while learner.ready:
        out.append(learner.update(learner.take()))
    return out


# --- the registry ------------------------------------------------------------------------------------------------

def test_the_registry_names_every_algorithm_and_refuses_what_is_not_one():
    assert algorithm_class("sac") is SACAlgorithm
    assert algorithm_class("ppo").name == "ppo" and algorithm_class("grpo").name == "grpo"
    with pytest.raises(ConfigError, match="algo.name = 'dqn': not one of ppo, grpo, sac"):
        load("quickstart", ["algo.name=dqn"])
    with pytest.raises(ValueError, match="not an ebrl.algos.algorithm.Algorithm"):
        algorithm_class("ebrl.algos.sac:SAC")
    with pytest.raises(ValueError, match="No module named 'no_such_pkg'"):
        algorithm_class("no_such_pkg.algo:Mine")


def test_sac_and_the_squashed_policy_go_together_and_train_on_one_rank():
    with pytest.raises(ConfigError, match="algo.name = 'sac' with policy.kind = 'mlp': that kind is trained by grpo"):
        load("sac_pendulum", ["policy.kind=mlp"])
    with pytest.raises(ConfigError, match="algo.name = 'ppo' with policy.kind = 'squashed': that kind is trained by"):
        load("sac_pendulum", ["algo.name=ppo"])  # the learner refuses it too (tests/test_policy_registry.py)
    with pytest.raises(ConfigError, match="sac trains on one rank"):
        load("sac_pendulum", ["train.world_size=2"])


def test_several_optimizers_save_and_load_as_one():
    nets = [torch.nn.Linear(3, 2), torch.nn.Linear(2, 1)]
    opts = [torch.optim.Adam(n.parameters(), lr=1e-3) for n in nets]
    for net, opt in zip(nets, opts):
        net(torch.ones(4, net.in_features)).sum().backward()
        opt.step()
    saved = Optimizers(opts).state_dict()
    assert sorted(saved["state"]) == [0, 1, 2, 3] and [g["params"] for g in saved["param_groups"]] == [[0, 1], [2, 3]]
    fresh = [torch.optim.Adam(n.parameters(), lr=1e-3) for n in nets]
    Optimizers(fresh).load_state_dict(saved)
    assert torch.equal(fresh[1].state_dict()["state"][0]["exp_avg"], opts[1].state_dict()["state"][0]["exp_avg"])
    with pytest.raises(ValueError, match="parameter groups"):
        Optimizers(fresh[:1]).load_state_dict(saved)


# --- SAC behind the learner --------------------------------------------------------------------------------------

@pytest.mark.slow  # 25-60 s; the fast suite's SAC run (test_sac_trains_in_a_real_run...) checks the ratio too
def test_sac_keeps_its_update_to_data_ratio_on_average_from_learning_starts(tmp_path):
    store = ReplayStore(3, 1, 10_000)
    learner, _ = sac_learner(tmp_path, "algo.utd=0.75", store=store)
    out = feed(learner, pendulum_segments(24))  # 384 decisions of one env step: 6 updates of 64
    steps = [o["gradient_steps"] for o in out]
    assert steps[0] == 0  # 64 transitions sent, fewer than learning_starts
    assert sum(steps) == int(0.75 * 64 * 5)  # from the update that reached it, 0.75 per env step
    assert set(steps[1:]) == {48.0}
    metrics = learner.metrics()
    assert metrics["train/utd"] == pytest.approx(0.75) and metrics["train/replay_sent"] == 384
    assert store.buffer.size == 384 and store.sampled == sum(steps) * 32
    assert learner.version == 6 and all(np.isfinite(o["critic_loss"]) for o in out[1:])


def test_without_keep_utd_an_update_learns_from_all_that_arrived_and_the_ratio_drops(tmp_path):
    learner, _ = sac_learner(tmp_path, "algo.keep_utd=false", "replay.learning_starts=0")
    for seg in pendulum_segments(12):  # 192 decisions arrive while training is busy
        learner.accept(seg, lambda exc: pytest.fail(str(exc)))
    out = learner.update(learner.take())
    assert out["batch_size"] == 192 and out["gradient_steps"] == 192  # the data it owes steps for
    assert not learner.ready


def test_an_empty_replay_leaves_the_gradient_steps_owed_until_it_holds_transitions_again(tmp_path):
    """A replay restarted without its file holds nothing: the update takes no step and owes them on."""
    store = ReplayStore(3, 1, 10_000)
    store.buffer.add_rows = lambda rows: 0  # holds nothing, whatever it is sent
    learner, _ = sac_learner(tmp_path, "replay.learning_starts=0", store=store)
    out = feed(learner, pendulum_segments(4))
    assert out[0]["gradient_steps"] == 0 and learner.algo.debt == 64
    del store.buffer.add_rows  # it holds what it is sent again: the steps owed are taken
    out = feed(learner, pendulum_segments(4, seed=1))
    assert out[0]["gradient_steps"] == 128 and learner.algo.debt == 0


def test_sac_resumes_its_critics_temperature_optimizers_and_counts(tmp_path):
    store = ReplayStore(3, 1, 10_000)
    learner, _ = sac_learner(tmp_path, "train.checkpoint_every=0", store=store)
    feed(learner, pendulum_segments(16))
    assert learner.save_checkpoint("sac-test")
    before = learner.algo
    again, telemetry = sac_learner(tmp_path, store=store)  # a restarted train: the replay service lives on
    assert again.resume(-1).startswith("train resumed at policy v4")
    after = again.algo
    for a, b in [(before.sac.critics, after.sac.critics), (before.sac.targets, after.sac.targets),
                 (before.model, after.model)]:
        assert all(torch.equal(x, y) for x, y in zip(a.state_dict().values(), b.state_dict().values()))
    assert after.sac.alpha == before.sac.alpha != 1.0
    assert torch.equal(after.sac.critic_opt.state_dict()["state"][0]["exp_avg"],
                       before.sac.critic_opt.state_dict()["state"][0]["exp_avg"])
    assert (after.sent, after.replay.acked, after.gradient_steps) == (256, 256, before.gradient_steps)
    assert after.model.warmup.item() == 0.0 and again.metrics()["train/utd"] == pytest.approx(1.0)
    feed(again, pendulum_segments(4, seed=1))  # a new session: its transitions are new, not a resend
    assert store.buffer.inserted == 320 and store.lost == 0


def test_a_checkpoint_of_another_algorithm_is_refused_saying_why(tmp_path, monkeypatch):
    learner, _ = sac_learner(tmp_path)
    feed(learner, pendulum_segments(8))
    learner.save_checkpoint("sac-test")
    with pytest.raises(ValueError, match="kind is 'squashed', the model's is 'mlp'"):
        Learner(load("quickstart", ["env.id=Pendulum-v1"]), INFO, 1, Counts(), str(tmp_path)).resume(-1)
    monkeypatch.syspath_prepend(str(TESTS))
    cfg = sac_config()
    cfg.algo.name = "user_algos:VanillaPG"  # the same actor under another algorithm (no config allows it)
    with pytest.raises(ValueError, match="algorithm's state does not fit: vanilla-pg keeps no state beyond"):
        Learner(cfg, INFO, 1, Counts(), str(tmp_path)).resume(-1)


# --- real runs ---------------------------------------------------------------------------------------------------

def test_a_users_own_algorithm_by_module_and_class_trains_in_a_real_run(tmp_path, monkeypatch):
    monkeypatch.setenv("PYTHONPATH", str(TESTS))  # the user's package, for the run's processes
    with up(tmp_path, "configs/quickstart.toml", "algo.name=user_algos:VanillaPG", "run.iterations=3",
            "train.batch_size=256", name="user-algo") as run, StatsWatcher(run) as stats:
        code = run.wait(240)
    assert code == 0, run.output
    assert stats.latest("train/0", "train/policy_version") == 3
    assert np.isfinite(stats.latest("train/0", "train/vpg_loss"))


def test_sac_trains_in_a_real_run_at_its_ratio_and_its_policy_loads_and_evaluates(tmp_path):
    with up(tmp_path, "configs/sac_pendulum.toml", *SMALL, "run.iterations=12", "run.target_return=",
            name="sac-run") as run, StatsWatcher(run) as stats:
        code = run.wait(240)
    assert code == 0, run.output
    assert stats.latest("train/0", "train/utd") == pytest.approx(1.0, rel=0.1)
    held = stats.latest("replay/0", "replay/size")
    assert held >= 700 and stats.latest("replay/0", "replay/sampled") > 500 * 32
    assert stats.latest("train/0", "train/gradient_steps_total") > 500
    assert "replay/0+train/0" in run.output  # the replay in training's process (run.processes = "auto")
    assert_catalogued(stats.reports())  # SAC's and the replay's metrics are on docs/stats.md
    with np.load(run.run_dir / REPLAY_FILE) as saved:  # written as the run ended
        assert int(saved["meta"][3]) == held
    policy = ebrl.load_policy(run.run_dir / "policy.safetensors")
    actions = np.stack([policy.predict(np.array([np.cos(a), np.sin(a), 0.0], np.float32))[0]
                        for a in np.linspace(-3, 3, 16)])
    assert actions.shape == (16, 1) and np.all(np.abs(actions) <= 2.0)
    evaluated = subprocess.run([sys.executable, "-m", "ebrl.cli", "eval", str(run.run_dir), "--episodes", "2"],
                               capture_output=True, text=True, timeout=120)
    assert evaluated.returncode == 0, evaluated.stderr
    assert "return" in evaluated.stdout


def test_keep_utd_decides_whether_generation_holds_simulators_back():
    from ebrl.sched.modes import resolve

    assert resolve(sac_config()).throttle and resolve(sac_config()).max_staleness == 1
    assert not resolve(sac_config("algo.keep_utd=false")).throttle  # simulators never wait; the ratio drops


@pytest.mark.slow  # a kill -9 and a restart (the fast suite has PPO's: tests/test_shared_process.py)
def test_a_killed_replay_restarts_with_its_contents_and_counts_what_it_lost(tmp_path):
    """The replay in a process of its own (``run.processes = []``), killed: training waits (sending its request
    again) while it restarts, reads back its last save and counts what training saw it take in since; every
    transition training sent is either in it or counted lost."""
    import signal

    from test_faults import service

    with up(tmp_path, "configs/sac_pendulum.toml", *SMALL, "run.iterations=30", "run.target_return=",
            "run.processes=[]", "replay.save_every_s=1", name="sac-kill") as run, StatsWatcher(run) as stats:
        stats.wait_for(lambda: (stats.latest("train/0", "train/policy_version") or 0) >= 12, 200, "policy v12")
        service(run, "replay").send_signal(signal.SIGKILL)
        code = run.wait(300)
    assert code == 0, run.output
    assert "replay/0 exited with status -9; restarting it" in run.output
    log = (run.run_dir / "logs" / "replay-0.log").read_text()
    restored = int(log.split("replay restored: ")[1].split()[0])  # its last save (every second)
    assert restored >= 5 * 64
    sent, lost = stats.latest("train/0", "train/replay_sent"), stats.latest("replay/0", "replay/lost")
    assert sent == 30 * 64 and sent == stats.latest("replay/0", "replay/inserted") + lost
    assert stats.latest("train/0", "train/utd") == pytest.approx(1.0, rel=0.1)


@pytest.mark.slow  # three real runs
@pytest.mark.parametrize("case, config, sets", [
    ("colocated", "configs/sac_pendulum.toml", [*SMALL, 'run.mode="colocated"', "run.iterations=8"]),
    ("a user's Dict observation", "configs/sac_pendulum.toml",
     [*SMALL, 'env.id="user_envs:DictPendulum-v0"', "run.iterations=8"]),
    ("mjwarp groups", "configs/mjwarp_pickcube.toml",
     ["algo.name=sac", "policy.kind=squashed", "policy.hidden=[32, 32]", "sim.envs_per_group=4",
      "train.batch_size=32", "replay.batch_size=32", "replay.learning_starts=64", "run.iterations=6"]),
], ids=lambda v: v if isinstance(v, str) and not v.startswith("configs") else "")
def test_sac_runs_in_colocated_mode_on_a_users_dict_observation_and_on_mjwarp_groups(tmp_path, monkeypatch, case,
                                                                                     config, sets):
    """Issue 53: SAC works in every mode (colocated: the synchronous baseline), with Dict observations (a user's
    env: its parts flattened by the layout into the replay's rows) and with vectorized MuJoCo Warp groups (packed
    segments), each a real `ebrl up` to its last iteration with gradient steps on the replay's minibatches."""
    monkeypatch.setenv("PYTHONPATH", str(TESTS))  # the user's env package, for the run's processes
    with up(tmp_path, config, *sets, "run.target_return=", "run.target_success=", 'viz.rerun="off"',
            name="sac-case") as run, StatsWatcher(run) as stats:
        code = run.wait(400)
    assert code == 0, run.output[-3000:]
    assert stats.latest("train/0", "train/gradient_steps_total") > 0, case
    assert stats.latest("replay/0", "replay/size") > 0 and stats.latest("replay/0", "replay/sampled") > 0, case
