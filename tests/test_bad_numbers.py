"""No bad step (issue 34): what a user's env returns and what arrives on the bus is bounded and checked before
training sees it; an update that is not finite is skipped, its data dropped; non-finite weights are never
published, saved, checkpointed or resumed from. Each is counted."""

from __future__ import annotations

import dataclasses
import json
import os
from pathlib import Path

import numpy as np
import pytest
import torch
from safetensors import safe_open
from safetensors.numpy import load_file
from safetensors.torch import save_file

from ebrl.algos import checkpoint
from ebrl.algos.learner import Learner
from ebrl import config
from ebrl.config import Config
from ebrl.envs import EnvSpec, describe
from ebrl.envs.batch import BatchRunner, EnvBatch
from ebrl.messages import SEGMENT_ENDS, SegmentBatch, TrajectorySegment
from ebrl.policies import state_arrays
from ebrl.testing import StatsWatcher
from helpers import Counts, up

CFG = Config()  # the default env: InvertedPendulum-v5
TESTS = Path(__file__).resolve().parent
INFO = describe(EnvSpec.from_config(CFG.env))


def learner(run_dir) -> tuple[Learner, Counts]:
    telemetry = Counts()
    return Learner(CFG, INFO, 4, telemetry, str(run_dir)), telemetry


def segment(T: int = 8, reward: float = 1.0) -> TrajectorySegment:
    rng = np.random.default_rng(0)
    obs_dim, (k, a) = INFO.obs_shape[0], (CFG.policy.chunk, INFO.action_dim)
    return TrajectorySegment(
        group=0, env_id=0, episode=0, obs=rng.normal(size=(T, obs_dim)).astype(np.float32),
        actions=np.zeros((T, k, a), np.float32), latents=np.zeros((T, 0), np.float32),
        logprobs=np.zeros(T, np.float32), values=np.zeros(T, np.float32), rewards=np.full(T, reward, np.float32),
        steps=np.full(T, k, np.int32), versions=np.zeros(T, np.int64), end="cut",
        last_obs=np.zeros(obs_dim, np.float32), episode_returns=[], episode_lengths=[])


def test_a_buggy_envs_rewards_and_observations_are_bounded_and_counted_in_a_batch():
    spec = EnvSpec("faulty_envs:BuggyReward-v0", max_abs_reward=100.0,
                   kwargs={"absurd_every": 3, "nan_every": 5, "inf_every": 7, "bad_obs_every": 11})
    runner = BatchRunner(EnvBatch(spec, [0, 1]), spec.max_abs_reward)
    runner.reset(np.zeros(2, np.int64))
    clipped = nonfinite = bad_obs = 0
    for _ in range(10):
        chunk = runner.chunk(np.zeros((2, 4, 1), np.float32))
        assert np.isfinite(chunk.reward).all() and np.all(np.abs(chunk.reward) <= 4 * 100.0)
        assert np.isfinite(chunk.next_obs).all() and np.isfinite(chunk.episode_return).all()
        clipped, nonfinite = clipped + chunk.rewards_clipped.sum(), nonfinite + chunk.rewards_nonfinite.sum()
        bad_obs += chunk.obs_nonfinite.sum()
        assert set(np.flatnonzero(chunk.obs_nonfinite)) <= set(chunk.ended)  # a broken state ends its episode
    assert clipped > 0 and nonfinite > 0 and bad_obs > 0


def test_train_drops_a_segment_whose_rewards_no_sim_could_send(tmp_path):
    learn, telemetry = learner(tmp_path)
    assert learn.accept(segment(reward=1e6 * CFG.policy.chunk), lambda exc: None)  # at the bound: taken
    assert not learn.accept(segment(reward=3.0e38), lambda exc: None)
    assert telemetry.counts == {"train/segments_received": 1, "train/reward_bound_dropped": 1}
    # an episode of 32 steps returns at most 32 times the bound: one that claims more is no sim's
    ok, forged = finished(segment(reward=0.0), 0.0, 32, True), finished(segment(reward=0.0), 1e9, 32, True)
    ok.env_id = 1
    assert learn.accept(ok, lambda exc: None) and not learn.accept(forged, lambda exc: None)
    assert telemetry.counts["train/reward_bound_dropped"] == 2
    metrics = learn.metrics()  # what the launcher ends a run on: the episodes of the segments taken
    assert (metrics["train/episode_return_mean"], metrics["train/success_rate"], metrics["train/episodes"],
            metrics["train/episode_length_max"]) == (0.0, 1.0, 1.0, 32.0)


def finished(seg: TrajectorySegment, ret: float, length: int, success: bool | None) -> TrajectorySegment:
    """``seg`` as the whole of an episode that ended with these values (its own, or forged)."""
    seg.end, seg.episode_offset = "terminated", 0
    seg.episode_returns, seg.episode_lengths, seg.episode_successes = [ret], [length], [success]
    return seg


def pack(segments: list[TrajectorySegment]) -> SegmentBatch:
    """``segments`` (at most one finished episode each) as one packed message, as a vectorized group sends them."""
    def cat(name):
        return np.concatenate([getattr(s, name) for s in segments])

    def ended(name, none, dtype):
        return np.array([getattr(s, name)[0] if getattr(s, name) else none for s in segments], dtype)

    return SegmentBatch(
        group=0, env_ids=np.array([s.env_id for s in segments]), episodes=np.array([s.episode for s in segments]),
        lengths=np.array([len(s.obs) for s in segments], np.int32),
        ends=np.array([SEGMENT_ENDS.index(s.end) for s in segments], np.int8),
        episode_offsets=np.array([s.episode_offset for s in segments], np.int64),
        **{name: cat(name) for name in ("obs", "actions", "latents", "logprobs", "values", "rewards", "steps",
                                         "versions")},
        last_obs=np.stack([s.last_obs for s in segments]), episode_returns=ended("episode_returns", 0.0, np.float32),
        episode_lengths=ended("episode_lengths", -1, np.int32),
        episode_successes=np.array([-1 if not s.episode_successes or s.episode_successes[0] is None else
                                    int(s.episode_successes[0]) for s in segments], np.int8))


def test_a_packed_batch_is_judged_segment_by_segment_as_its_segments_would_be(tmp_path):
    """Taking a vectorized group's packed segments in one go keeps and drops exactly what taking them one at a
    time does: the same counts, the same pending decisions, the same episodes behind the stop rule."""
    one_bad_decision = segment(reward=1.0)
    one_bad_decision.rewards[3] = 3.0e38
    future = segment(T=3)
    future.versions[-1] = 1  # acted by a version this learner never published
    # rewards of 0 (an episode of them counts at once, before a learned reward bound is known)
    segments = [finished(segment(T=5, reward=0.0), 0.0, 20, True), segment(reward=3.0e38), one_bad_decision, future,
                finished(segment(T=2, reward=0.0), 1e9, 8, True), finished(segment(T=4, reward=0.0), 0.0, 16, None),
                finished(segment(T=1, reward=0.0), 0.0, 4, False), segment(T=6),
                finished(segment(T=2, reward=0.0), 0.0, 8, True), finished(segment(T=3, reward=0.0), 5.0, 12, True)]
    for i, seg in enumerate(segments):
        seg.env_id, seg.obs = i, seg.obs + i  # each segment's own observations
    one, one_counts = learner(tmp_path / "one")
    taken = [one.accept(seg, pytest.fail) for seg in segments]
    assert taken == [1, 0, 0, 0, 0, 1, 1, 1, 1, 0]  # the last forges its episode's return
    packed_learner, packed_counts = learner(tmp_path / "packed")
    batch = pack(segments)
    batch.check()
    assert packed_learner.accept(batch, pytest.fail) == sum(taken)
    assert packed_counts.counts == one_counts.counts == {
        "train/segments_received": 5, "train/reward_bound_dropped": 3, "train/future_version_dropped": 1}
    assert packed_learner.metrics() == one.metrics()
    metrics = packed_learner.metrics()
    assert (metrics["train/episodes"], metrics["train/success_rate"], metrics["train/episode_values_refused"]) == \
        (4, 2 / 3, 1)
    pending = [np.concatenate([s.obs for s in learned.collector.segments()]) for learned in (one, packed_learner)]
    assert np.array_equal(*pending)


def test_weights_that_turned_non_finite_are_never_published_and_the_last_good_ones_come_back(tmp_path):
    learn, telemetry = learner(tmp_path)
    learn.sync(1)
    good = {k: v.copy() for k, v in learn.arrays.items()}
    with torch.no_grad():
        next(learn.model.parameters()).fill_(float("nan"))
    learn.sync(2)
    assert telemetry.counts == {"train/weights_refused": 1}
    for name, array in good.items():
        np.testing.assert_array_equal(learn.arrays[name], array)
        np.testing.assert_array_equal(state_arrays(learn.model)[name], array)  # the model is back too


def test_a_non_finite_state_is_never_checkpointed_saved_or_resumed_from(tmp_path):
    learn, telemetry = learner(tmp_path)
    learn.version = 3
    assert learn.save_checkpoint("r")
    with torch.no_grad():
        next(learn.model.parameters()).fill_(float("inf"))
    learn.version = 4
    assert not learn.save_checkpoint("r")  # refused, counted; v3 stays the newest
    assert telemetry.counts["train/checkpoints_refused"] == 1
    assert [p.name for p in checkpoint.candidates(tmp_path)] == ["v00000003"]
    learn.arrays = state_arrays(learn.model)
    assert learn.save_policy("r") is None and not (tmp_path / "policy.safetensors").exists()

    # one written by other means (an older EBRL, a hand-made file): skipped at resume, the one before taken
    forged = checkpoint.checkpoint_dir(tmp_path) / "v00000005"
    forged.mkdir()
    source = checkpoint.checkpoint_dir(tmp_path) / "v00000003"
    for name in ("policy.safetensors", "train.safetensors"):
        (forged / name).write_bytes((source / name).read_bytes())
    (forged / "state.json").write_text(json.dumps({**json.loads((source / "state.json").read_text()), "version": 5}))
    with safe_open(str(forged / "policy.safetensors"), "pt") as fh:
        metadata = fh.metadata()
    weights = {k: torch.from_numpy(v) for k, v in load_file(str(forged / "policy.safetensors")).items()}
    next(iter(weights.values())).fill_(float("nan"))
    save_file(weights, str(forged / "policy.safetensors"), metadata)
    fresh, _ = learner(tmp_path)
    assert fresh.resume(-1) is not None and fresh.version == 6  # v3's weights, continuing after every version seen
    assert all(np.isfinite(a).all() for a in fresh.arrays.values())


@pytest.fixture(scope="module")
def buggy_run(tmp_path_factory):
    """The quickstart on InvertedPendulum with a user's numeric bugs: absurd (1e38), NaN and -inf rewards every few
    hundred steps of every env, and NaN observations every 101st. The worker checks every reward but only the
    observation a chunk ends on (the one the policy reads): with 607 between bad observations, a run of 10
    iterations could see none at a chunk's end (1 failure in a full suite); at 101, some 100 in the run."""
    out = tmp_path_factory.mktemp("buggy")
    kwargs = '{absurd_every = 300, nan_every = 401, inf_every = 503, bad_obs_every = 101}'
    with pytest.MonkeyPatch.context() as patch:
        patch.setenv("PYTHONPATH", os.pathsep.join([str(TESTS), os.environ.get("PYTHONPATH", "")]))  # faulty_envs
        # the quickstart's own target return (900): one clipped 1e38 reward (1e6) in an episode must not reach it
        with up(out, "configs/quickstart.toml", "run.iterations=10", "train.batch_size=256", 'viz.rerun="off"', 'env.id="faulty_envs:BuggyReward-v0"',
                f"env.kwargs={kwargs}", name="buggy") as run, \
                StatsWatcher(run) as stats:
            code = run.wait(300)
    return run, stats, code


def test_a_run_on_a_buggy_env_finishes_every_iteration_with_no_restart_and_a_finite_policy(buggy_run):
    run, stats, code = buggy_run
    assert code == 0, run.output
    summary = json.loads((run.run_dir / "summary.json").read_text())
    assert summary["iterations"] == 10 and summary["restarts"] == {}
    # no early end: the episodes with a clipped absurd reward were trained on but did not count
    assert summary["target_reached"] is None and stats.latest("train/0", "train/episodes_past_bound", 0) > 0
    assert all(v <= 1000.0 for v in stats.values("train/0", "train/episode_return_mean"))  # InvertedPendulum's most
    assert summary["final_return"] is not None and summary["final_return"] <= 1000.0  # the real return
    for name in ("sim/rewards_clipped", "sim/rewards_nonfinite", "sim/obs_nonfinite"):
        assert stats.latest("sim/0", name, 0) > 0, name
    assert stats.latest("train/0", "train/reward_bound_dropped", 0) == 0  # the sim bounded them all
    policy = load_file(str(run.run_dir / "policy.safetensors"))
    assert all(np.isfinite(a).all() for a in policy.values())
    report = (run.run_dir / "report" / "report.md").read_text()
    assert "sim/rewards_clipped" in report


@pytest.mark.slow  # the fast suite's 10 minutes; the weights' plausibility unit tests stay fast
def test_one_forged_weights_version_ahead_of_train_does_not_stall_the_run(tmp_path):
    """The issue's case: one plausible weights message -- train's newest tensors numbered its version + 60 --
    put gen ahead of train, train dropped every later segment as acted by a future version, and the run stood
    still for good. Now gen goes back to train's weights and the run finishes, nothing restarted."""
    import asyncio

    from ebrl import keys
    from ebrl.messages import Weights
    from helpers import loopback_bus

    async def forge(port: int, run: str) -> int:
        bus = loopback_bus(port, listen=False)
        try:
            sub = bus.subscribe(keys.weights(run), Weights, policy="latest", capacity=1)
            _, real = await asyncio.wait_for(sub.next(), 120)
            await bus.put(keys.weights(run), dataclasses.replace(real, version=real.version + 60))
            await asyncio.sleep(0.5)
            return real.version + 60
        finally:
            await bus.close()

    # 16 iterations: the forger subscribes once v3 is seen and must still catch a weights publish (with 10 the
    # run could end first and it waited for one in vain)
    with up(tmp_path, "configs/quickstart.toml", "run.iterations=16", "train.batch_size=256", 'viz.rerun="off"',
            "bus.auth=false", "train.checkpoint_every=0", name="forged") as run, StatsWatcher(run) as stats:
        stats.wait_for(lambda: (stats.latest("train/0", "train/policy_version") or 0) >= 3, 300, "policy v3")
        forged = asyncio.run(forge(run.port, run.name))
        stats.wait_for(lambda: (stats.latest("gen/0", "gen/policy_version") or 0) >= forged, 30, "gen at the forgery")
        code = run.wait(300)
    assert code == 0, run.output
    summary = json.loads((run.run_dir / "summary.json").read_text())
    assert summary["iterations"] == 16 and summary["restarts"] == {}
    assert stats.latest("gen/0", "gen/version_resets") >= 1  # it went back to train's weights, on its own


def test_on_policy_data_weighs_one_in_the_decoupled_objective_while_the_normaliser_moves(tmp_path):
    """pi_prox is the policy that acted, taken before the batch joins the observation statistics: on-policy
    data far from the statistics so far has w = 1, and the decoupled update is plain PPO's, weight for weight."""
    weights, stats = {}, {}
    for decoupled in (True, False):
        raw: dict = {}
        for item in ("policy.normalize_obs=true", f"algo.decoupled={str(decoupled).lower()}",
                     "algo.prox_logp=recompute", "train.batch_size=8"):
            config.apply_override(raw, item)
        cfg = config.from_dict(raw)
        learner = Learner(cfg, INFO, 4, Counts(), str(tmp_path / str(decoupled)))
        seg = segment()
        seg.obs = seg.obs * 50.0 + 20.0  # the statistics move a long way with this batch
        k, a = cfg.policy.chunk, INFO.action_dim
        seg.actions = np.random.default_rng(1).normal(size=(len(seg.obs), k, a)).astype(np.float32)
        with torch.no_grad():  # the log-probs of the policy that acted: version 0, statistics before the batch
            seg.logprobs = learner.model.evaluate(torch.as_tensor(seg.obs), torch.as_tensor(seg.actions),
                                                  torch.zeros(len(seg.obs), 0))[0].numpy()
        assert learner.accept(seg, pytest.fail)
        stats[decoupled] = learner.learn(learner.take())
        weights[decoupled] = state_arrays(learner.model)
    assert stats[True]["behave_weight_mean"] == pytest.approx(1.0, abs=1e-6)
    assert stats[True]["behave_kl"] == pytest.approx(0.0, abs=1e-6)
    for name, value in weights[False].items():
        np.testing.assert_allclose(weights[True][name], value, rtol=1e-5, atol=1e-6, err_msg=name)
