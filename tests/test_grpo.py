"""GRPO: group-relative advantages on hand-made groups, episode assembly, shared initial states, config."""

import asyncio
from types import SimpleNamespace

import numpy as np
import pytest
import torch

from ebrl import config
from ebrl.algos.grpo import GroupCollector, group_advantages
from ebrl.algos.ppo import PPO
from ebrl.config import PolicySection
from ebrl.envs import EnvSpec, EnvWorker, ObsLayout
from ebrl.messages import TrajectorySegment
from ebrl.policies import make_policy
from ebrl.sched.modes import resolve

ALGO = SimpleNamespace(name="grpo", group_size=2, gamma=1.0, gae_lambda=1.0, clip=0.2, epochs=4, minibatches=1,
                       ent_coef=0.0, vf_coef=0.5, max_grad_norm=0.5, decoupled=True, behave_weight_cap=5.0)


def seg(env, episode, rewards, end="cut", versions=None, obs_value=0.0):
    T = len(rewards)
    return TrajectorySegment(
        group=0, env_id=env, episode=episode, obs=np.full((T, 3), obs_value, np.float32),
        actions=np.zeros((T, 2, 1), np.float32), latents=np.zeros((T, 0), np.float32),
        logprobs=np.zeros(T, np.float32), values=np.zeros(T, np.float32),
        rewards=np.asarray(rewards, np.float32), steps=np.full(T, 2, np.int32),
        versions=np.asarray(versions if versions is not None else [0] * T, np.int64),
        end=end, last_obs=np.zeros(3, np.float32), episode_returns=[], episode_lengths=[])


def collector(max_pending=1000, max_staleness=1, group_size=2):
    counts = {}
    c = GroupCollector(SimpleNamespace(**{**vars(ALGO), "group_size": group_size}), max_pending, max_staleness,
                       lambda k, n: counts.__setitem__(k, counts.get(k, 0) + n))
    return c, counts


def test_group_advantages_by_hand():
    np.testing.assert_allclose(group_advantages([1.0, 2.0, 3.0, 6.0]),
                               (np.array([1, 2, 3, 6]) - 3.0) / np.sqrt((4 + 1 + 0 + 9) / 4), rtol=1e-5)
    np.testing.assert_array_equal(group_advantages([5.0, 5.0, 5.0]), np.zeros(3, np.float32))


def test_a_group_is_ready_when_every_member_finished_the_same_episode():
    c, counts = collector()
    c.add(seg(0, 0, [1.0, 1.0]))  # env 0, episode 0, first part
    c.add(seg(1, 0, [0.0], end="terminated"))  # env 1 finished episode 0: return 0
    assert c.ready_steps == 0 and c.pending_steps == 3
    c.add(seg(2, 0, [9.0], end="terminated"))  # another group (envs 2, 3): not ready
    c.add(seg(0, 0, [1.0], end="truncated"))  # env 0 finished episode 0: return 3
    assert c.ready_steps == 4 and counts == {"train/grpo_groups": 1}
    items = c.take(version=0, batch_size=4)
    by_env = {e.env_id: (adv, e.decisions) for e, adv, _ in items}
    assert by_env[0][0] == pytest.approx(1.0, abs=1e-5) and by_env[1][0] == pytest.approx(-1.0, abs=1e-5)
    assert by_env[0][1] == 3 and by_env[1][1] == 1
    batch = c.build(items, None)
    assert batch.returns is None and not batch.normalize_advantages
    np.testing.assert_allclose(sorted(batch.advantages.tolist()), [-1, 1, 1, 1], atol=1e-5)
    assert c.pending_steps == 1 and c.ready_steps == 0  # env 2's episode still waits for env 3


def test_episodes_with_a_gap_are_dropped_and_the_bound_holds():
    c, counts = collector(max_pending=4)
    c.add(seg(0, 0, [1.0]))
    c.add(seg(0, 1, [1.0], end="terminated"))  # episode 0's end never arrived
    assert counts["train/grpo_episodes_incomplete"] == 1 and c.pending_steps == 1
    for ep in range(2, 6):  # env 0 finishes episodes, env 1 never does: groups pile up unfinished
        c.add(seg(0, ep, [1.0, 1.0], end="terminated"))
    assert c.pending_steps <= 4 and counts["train/grpo_groups_dropped_overflow"] >= 1


def test_stale_decisions_are_masked_but_count_in_the_return():
    c, counts = collector(max_staleness=1)
    c.add(seg(0, 0, [5.0, 0.0], versions=[0, 3], end="terminated"))
    c.add(seg(1, 0, [0.0, 0.0], versions=[3, 3], end="terminated"))
    items = c.take(version=3, batch_size=1)
    assert counts["train/stale_dropped"] == 1
    batch = c.build(items, None)
    assert len(batch) == 3 and batch.versions.tolist().count(0) == 0
    env0 = next(adv for e, adv, _ in items if e.env_id == 0)
    assert env0 > 0  # its return of 5 still counts although its first decision was too stale to train on


def test_grpo_update_moves_probability_towards_the_better_rollout():
    torch.manual_seed(0)
    policy = make_policy(PolicySection(kind="mlp", chunk=2, hidden=[16], init_log_std=-0.5, channels=[8],
                                       embed_dim=8, denoise_steps=2, checkpoint=""), ObsLayout.vector(3), 1)
    obs = np.zeros((16, 3), np.float32)
    actions, logprobs, values, latents = policy.act(obs)
    good = actions.reshape(16, -1).mean(1) > 0
    c, _ = collector(group_size=2)
    for i in range(8):  # 8 groups of 2 one-decision episodes: one rollout with a positive mean action
        for member, j in enumerate((2 * i, 2 * i + 1)):
            s = seg(2 * i + member, 0, [float(good[j])], end="terminated")
            c.add(TrajectorySegment(**{**s.__dict__, "actions": actions[j:j + 1], "logprobs": logprobs[j:j + 1],
                                       "latents": latents[j:j + 1]}))
    batch = c.build(c.take(0, 16), policy)
    before = policy.dist(torch.zeros(1, 3)).mean.mean().item()
    PPO(policy, ALGO, lr=1e-2).update(batch)
    assert policy.dist(torch.zeros(1, 3)).mean.mean().item() > before


def test_envs_of_a_group_replay_the_same_initial_states():
    async def scenario():
        spec = EnvSpec("user_envs:ShortPendulum-v0")  # 10-step episodes
        a, b, other = EnvWorker(spec, seed=42), EnvWorker(spec, seed=42), EnvWorker(spec, seed=43)
        try:
            first = await asyncio.gather(a.reset(), b.reset(), other.reset())
            np.testing.assert_array_equal(first[0], first[1])
            assert not np.array_equal(first[0], first[2])
            ra = await a.chunk(np.full((12, 1), 0.5, np.float32))  # different actions, same next start
            rb = await b.chunk(np.full((12, 1), -0.5, np.float32))
            assert (ra.terminated or ra.truncated) and (rb.terminated or rb.truncated) and ra.episode == rb.episode == 0
            np.testing.assert_array_equal(ra.next_obs, rb.next_obs)
            assert not np.array_equal(ra.next_obs, first[0])  # episode 1 starts elsewhere
            nxt = await a.chunk(np.zeros((1, 1), np.float32))
            assert nxt.episode == 1
        finally:
            for w in (a, b, other):
                w.close()

    asyncio.run(scenario())


def test_grpo_config_checks_the_group_size():
    raw = {"algo": {"name": "grpo", "group_size": 3}, "sim": {"groups": 2, "envs_per_group": 4},
           "train": {"batch_size": 64}}
    with pytest.raises(config.ConfigError, match="algo.group_size = 3"):
        config.from_dict(raw)
    raw["algo"]["group_size"] = 4
    assert config.from_dict(raw).algo.name == "grpo"


def test_grpo_needs_rollout_and_training_to_overlap():
    raw = {"run": {"mode": "colocated"}, "algo": {"name": "grpo", "group_size": 4},
           "sim": {"groups": 2, "envs_per_group": 4}, "train": {"batch_size": 64}}
    with pytest.raises(config.ConfigError, match="whole episodes"):
        config.from_dict(raw)
    raw["train"]["overlap"] = True
    schedule = resolve(config.from_dict(raw), cores=[0, 1])
    assert not schedule.throttle and schedule.min_version(10_000) == -1  # generation is never held back


def test_group_mates_run_their_episodes_together():
    from ebrl.sched.rollout import Episodes

    async def scenario():
        episodes = Episodes(range(4), share=2)  # groups {0, 1} and {2, 3}
        assert list(episodes.members(3)) == [2, 3] and all(episodes.may_act(e) for e in range(4))
        episodes.set(0, 1)  # env 0 finished episode 0: it waits for env 1
        assert not episodes.may_act(0) and episodes.may_act(1) and episodes.may_act(2)
        waiter = asyncio.ensure_future(episodes.moved())
        await asyncio.sleep(0)
        episodes.set(1, 1)
        await asyncio.wait_for(waiter, 1)
        assert episodes.may_act(0) and episodes.may_act(1)
        assert all(Episodes(range(4)).may_act(e) for e in range(4))  # PPO: nobody waits

    asyncio.run(scenario())


def test_what_a_stopping_train_hands_over_rebuilds_the_same_groups():
    c, _ = collector()
    for s in (seg(0, 0, [1.0, 1.0]), seg(1, 0, [0.0], end="terminated"), seg(2, 0, [9.0], end="terminated"),
              seg(0, 0, [1.0], end="truncated"), seg(3, 1, [2.0])):
        c.add(s)
    again, _ = collector()
    for s in c.segments():  # the order hand_over writes them in
        again.add(s)
    assert (again.ready_steps, again.pending_steps) == (c.ready_steps, c.pending_steps) == (4, 6)
    assert sorted(e.env_id for e, _, _ in again.take(version=0, batch_size=4)) == [0, 1]


def test_rank_commands_travel_as_messages_never_as_pickles():
    """What rank 0 sends the other training ranks (ebrl.algos.parallel): EBRL's codec, each segment validated
    as any message is; anything else (a pickle, a bad kind, a mask that does not fit) is refused."""
    import pickle

    from ebrl.algos.parallel import Command, decode_command, encode_command
    from ebrl.algos.ppo import SegmentCollector
    from ebrl.messages import MessageError

    c, _ = collector()
    c.add(seg(0, 0, [1.0, 1.0], end="terminated"))
    c.add(seg(1, 0, [0.0], end="terminated"))
    items = c.take(version=0, batch_size=4)
    back = decode_command(encode_command(Command("update", items), GroupCollector), GroupCollector)
    assert back.kind == "update" and len(back.items) == 2
    for (episode, adv, fresh), (episode2, adv2, fresh2) in zip(items, back.items):
        assert (episode2.env_id, episode2.index, adv2) == (episode.env_id, episode.index, adv)
        np.testing.assert_array_equal(fresh2, fresh)
        np.testing.assert_array_equal(episode2.cat("rewards"), episode.cat("rewards"))
    segment = seg(0, 1, [0.5])
    (got,) = decode_command(encode_command(Command("update", [segment]), SegmentCollector), SegmentCollector).items
    np.testing.assert_array_equal(got.rewards, segment.rewards)
    assert decode_command(encode_command(Command("stop"), SegmentCollector), SegmentCollector).items is None
    from ebrl import codec

    for payload in (pickle.dumps(Command("stop")), codec.encode({"kind": "exec", "items": None}),
                    codec.encode({"kind": "update", "items": [{"segments": [], "fresh": [True], "advantage": 1.0}]})):
        with pytest.raises((MessageError, codec.DecodeError)):
            decode_command(payload, GroupCollector)
