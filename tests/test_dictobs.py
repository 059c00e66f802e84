"""Dict observations (ebrl/envs/dictobs.py): a gymnasium env with a (nested) Dict observation trains and acts with
no wrapper written by its user; spaces EBRL cannot read or drive are refused naming the space."""

import dataclasses
import importlib.util
import json
from pathlib import Path

import gymnasium as gym
import helpers
import numpy as np
import pytest
import torch

import ebrl
from ebrl.config import Config, PolicySection
from ebrl.envs import EnvError, EnvSpec, describe, make_env, tokenize
from ebrl.envs.backends import check_spaces, lazy_observer
from ebrl.envs.dictobs import DictObservation, layout_of, pack, pack_batch
from ebrl.envs.latency import StepLatency
from ebrl.policies import make_policy, save_checkpoint
from ebrl.policies.checkpoint import portable_metadata

TESTS = Path(__file__).resolve().parent
S = gym.spaces
GOAL_IMAGE = "user_envs:GoalImage-v0"  # tests/user_envs.py: camera/rgb 16x16x3, robot/position, goal, task (Text)
SPACE = S.Dict({
    "obs": S.Dict({"cam": S.Box(0, 255, (8, 6, 3), np.uint8), "joints": S.Box(-1, 1, (2, 2), np.float32)}),
    "goal": S.Box(-np.inf, np.inf, (3,), np.float64),
    "mode": S.Discrete(4),
    "contacts": S.MultiBinary(2),
    "task": S.Text(32, charset="abcdefghijklmnopqrstuvwxyz "),
})


def sample(seed: int = 0) -> dict:
    rng = np.random.default_rng(seed)
    return {"obs": {"cam": rng.integers(0, 256, (8, 6, 3), dtype=np.uint8),
                    "joints": rng.uniform(-1, 1, (2, 2)).astype(np.float32)},
            "goal": rng.normal(size=3), "mode": np.int64(2), "contacts": np.array([1, 0], np.int8),
            "task": "open the drawer"}


class DictEnv(gym.Env):
    """An env of any observation and action space, whose observation is ``obs`` (``sample()`` by default)."""

    def __init__(self, observation_space=SPACE, action_space=None, obs=None):
        self.observation_space = observation_space
        self.action_space = action_space or S.Box(-1.0, 1.0, (2,), np.float32)
        self.obs = sample() if obs is None else obs

    def reset(self, *, seed=None, options=None):
        super().reset(seed=seed)
        return self.obs, {}

    def step(self, action):
        return self.obs, 0.0, False, False, {}


# --- the layout and the conversion ------------------------------------------------------------------------------


def test_each_leaf_becomes_a_field_of_its_kind_named_by_its_key_path():
    layout = layout_of(SPACE)
    assert layout.describe() == ("contacts:vector[2] + goal:vector[3] + mode:vector[1] + obs/cam:image[3, 8, 6] + "
                                 "obs/joints:vector[4] + task:tokens[16]")  # gymnasium sorts a plain dict's keys
    obs = sample()
    parts = layout.split(pack(layout, obs)[None])
    assert np.allclose(parts["obs/cam"][0], obs["obs"]["cam"].transpose(2, 0, 1) / 255)  # channel-first, [0, 1]
    assert np.allclose(parts["obs/joints"][0], obs["obs"]["joints"].ravel())
    assert np.allclose(parts["goal"][0], obs["goal"]) and parts["mode"][0, 0] == 2
    assert list(parts["contacts"][0]) == [1, 0]
    assert np.array_equal(parts["task"][0], tokenize("open the drawer"))


def test_obs_keys_select_and_order_the_fields_and_an_inner_dict_selects_its_leaves():
    layout = layout_of(SPACE, ["goal", "obs"])
    assert [f.name for f in layout.fields] == ["goal", "obs/cam", "obs/joints"]
    assert [f.name for f in layout_of(SPACE, ["obs/joints", "task", "goal"]).fields] == ["obs/joints", "task", "goal"]
    with pytest.raises(EnvError, match=r"no observation key 'goals'; its keys: 'contacts', 'goal', 'mode', "
                                       r"'obs/cam', 'obs/joints', 'task'"):
        layout_of(SPACE, ["goal", "goals"])


def test_a_batch_converts_as_a_dict_of_batched_values_or_a_list_of_dicts():
    layout = layout_of(SPACE)
    obs = [sample(i) for i in range(3)]
    flat = np.stack([pack(layout, o) for o in obs])
    batched = {"obs": {"cam": np.stack([o["obs"]["cam"] for o in obs]),
                       "joints": np.stack([o["obs"]["joints"] for o in obs])},
               "goal": np.stack([o["goal"] for o in obs]), "mode": np.array([2, 2, 2]),
               "contacts": np.stack([o["contacts"] for o in obs]), "task": tuple(o["task"] for o in obs)}
    for given in (batched, obs):
        out, single = pack_batch(layout, given)
        assert not single and np.allclose(out, flat)
    out, single = pack_batch(layout, obs[0])
    assert single and np.allclose(out, flat[:1])


def test_an_observation_that_does_not_match_its_space_is_an_error_naming_the_key():
    wrapped = DictObservation(DictEnv(obs={**sample(), "obs": {"cam": np.zeros((6, 8, 3), np.uint8),
                                                               "joints": np.zeros(4)}}), env_id="mine")
    with pytest.raises(EnvError, match=r"mine: observation key 'obs/cam' is an image of shape \(6, 8, 3\); its "
                                       r"space says \(8, 6, 3\)"):
        wrapped.reset()
    missing = DictObservation(DictEnv(obs={k: v for k, v in sample().items() if k != "goal"}), env_id="mine")
    with pytest.raises(EnvError, match="mine: observation has no key 'goal'"):
        missing.reset()
    wrong_text = DictObservation(DictEnv(obs={**sample(), "task": 7}), env_id="mine")
    with pytest.raises(EnvError, match="observation key 'task' is text; got int"):
        wrong_text.reset()


def test_an_image_out_of_its_byte_range_is_clipped_and_a_non_finite_vector_left_to_the_guard():
    obs = {**sample(), "goal": np.array([np.nan, 0, 0]), "obs": {"cam": np.full((8, 6, 3), 999.0),
                                                                  "joints": np.zeros((2, 2))}}
    flat, _ = DictObservation(DictEnv(obs=obs)).reset()
    parts = layout_of(SPACE).split(flat[None])
    assert np.all(parts["obs/cam"] == 1.0) and np.isnan(parts["goal"][0, 0])  # ebrl.envs.guard ends the episode


class LazyDictEnv(DictEnv):
    """A Dict env that renders its camera only when asked (``skip_observation``, ``observe()``), as robosuite's."""

    skip_observation = False

    def step(self, action):
        obs = {**self.obs, "obs": {**self.obs["obs"], "cam": np.zeros((8, 6, 3), np.uint8)}}
        return (obs if self.skip_observation else self.obs), 0.0, False, False, {}

    def observe(self):
        return self.obs


def test_a_lazily_rendering_dict_env_is_observed_through_the_adapter():
    env = StepLatency(DictObservation(LazyDictEnv()), mean_ms=0.01, sigma=0.0)
    observer = lazy_observer(env)
    assert isinstance(observer, DictObservation)
    observer.skip_observation = True
    assert env.unwrapped.skip_observation is True
    skipped = env.step(np.zeros(2, np.float32))[0]
    assert np.allclose(observer.observe(), pack(layout_of(SPACE), sample())) and not np.allclose(skipped,
                                                                                                 observer.observe())
    assert lazy_observer(DictObservation(DictEnv())) is None


# --- what EBRL refuses ----------------------------------------------------------------------------------------------


@pytest.mark.parametrize("space,message", [
    (S.Discrete(3), r"action space Discrete\(3\) is not supported: EBRL drives continuous actions, a 1-d Box "
                    r"\(low, high, \(n,\)\) \(discrete actions are not"),
    (S.Dict({"arm": S.Box(-1, 1, (2,))}), r"action space Dict\('arm': Box.*is not supported: EBRL drives continuous "
                                          r"actions, a 1-d Box"),
    (S.Box(-1, 1, (2, 3)), r"action space Box.*\(2, 3\).* is not supported.*flatten it to 1-d"),
])
def test_an_action_space_ebrl_cannot_drive_is_refused_naming_it_and_what_is_supported(space, message):
    with pytest.raises(EnvError, match=message):
        check_spaces("mine", SPACE, space)


def test_an_observation_space_ebrl_cannot_read_is_refused_naming_the_key_and_what_is_supported():
    graph = S.Graph(node_space=S.Box(-1, 1, (3,)), edge_space=None)
    with pytest.raises(EnvError, match=r"mine: observation key 'world/scene' has the space Graph.*cannot read; "
                                       r"a Dict observation's leaves may be a uint8 Box \(H, W, C\)"):
        check_spaces("mine", S.Dict({"world": S.Dict({"scene": graph})}), S.Box(-1, 1, (2,)))
    with pytest.raises(EnvError, match=r"observation space Discrete\(5\) is not supported: EBRL reads a Box .* or a "
                                       r"Dict, nested too"):
        check_spaces("mine", S.Discrete(5), S.Box(-1, 1, (2,)))


def test_obs_keys_for_an_env_without_a_dict_observation_is_an_error():
    with pytest.raises(EnvError, match=r"env.obs_keys = \['goal'\] selects keys of a Dict observation; "
                                       r"InvertedPendulum-v5's observation space is Box"):
        make_env(EnvSpec("InvertedPendulum-v5", obs_keys=("goal",)))


# --- a user's env, built as EBRL builds it -----------------------------------------------------------------------


@pytest.fixture
def user_envs(monkeypatch):
    monkeypatch.syspath_prepend(str(TESTS))
    monkeypatch.setenv("PYTHONPATH", str(TESTS))  # the user's env package, for the run's processes


def test_make_env_adapts_a_nested_dict_env_and_describe_reads_its_layout(user_envs):
    info = describe(EnvSpec(GOAL_IMAGE))
    assert info.layout.describe() == ("camera/rgb:image[3, 16, 16] + goal:vector[2] + robot/position:vector[2] + "
                                      "task:tokens[16]")
    assert info.obs_shape == (info.layout.size,)
    env = make_env(EnvSpec(GOAL_IMAGE, obs_keys=("goal", "camera")))
    obs, _ = env.reset(seed=1)
    assert obs.shape == (2 + 3 * 16 * 16,) and obs.dtype == np.float32 and env.observation_space.contains(obs)
    _, _, _, _, info = env.step(np.zeros(2, np.float32))
    assert info["success"] is False and "is_success" in info  # gymnasium-robotics' key, as EBRL's


def test_predict_takes_the_dict_the_env_returns(user_envs, tmp_path):
    cfg = dataclasses.replace(Config(), env=dataclasses.replace(Config().env, id=GOAL_IMAGE))
    info = describe(EnvSpec.from_config(cfg.env))
    policy_cfg = PolicySection(kind="cnn", chunk=2, hidden=[16], channels=[4], embed_dim=8)
    torch.manual_seed(0)
    model = make_policy(policy_cfg, info.layout, info.action_dim)
    save_checkpoint(model, str(tmp_path / "p.safetensors"), portable_metadata(policy_cfg, cfg.env, info))
    policy = ebrl.load_policy(tmp_path / "p.safetensors")
    raw = gym.make(GOAL_IMAGE)
    obs, _ = raw.reset(seed=3)
    flat, _ = policy.make_env().reset(seed=3)
    assert np.allclose(policy.predict_chunk(obs), policy.predict_chunk(flat))
    action, _ = policy.predict(obs)
    assert action.shape == (2,)
    vec = gym.make_vec(GOAL_IMAGE, num_envs=3, vectorization_mode="sync")
    batch, _ = vec.reset(seed=0)
    actions, _ = policy.predict(batch)
    assert actions.shape == (3, 2)
    vec.close()


def test_a_users_nested_dict_env_with_an_image_and_a_goal_trains_through_ebrl_up(user_envs, tmp_path):
    """The issue's acceptance: a user's own Dict-observation env trains with no wrapper, and its trained policy
    acts on the env's own Dict."""
    code, out, stats = helpers.run_collecting_stats(
        tmp_path / "runs", "configs/quickstart.toml", "run.iterations=2", f'env.id="{GOAL_IMAGE}"',
        'policy.kind="cnn"', "policy.channels=[8]", "policy.embed_dim=32", "sim.envs_per_group=2",
        "train.batch_size=64", run="dictobs")
    assert code == 0, out
    summary = json.loads(next((tmp_path / "runs").glob("dictobs-*/summary.json")).read_text())
    # episodes ended (the simulator's count: training counts an episode only once it learned its reward bound,
    # after 1000 nonzero rewards, more than this 2-iteration run makes; ebrl.algos.returns)
    assert summary["env_steps"] > 0 and summary["sim"]["episodes"] > 0
    policy = ebrl.load_policy(next((tmp_path / "runs").glob("dictobs-*")))
    assert [f.name for f in policy.layout.fields] == ["camera/rgb", "goal", "robot/position", "task"]
    obs, _ = gym.make(GOAL_IMAGE).reset(seed=0)
    assert policy.predict(obs)[0].shape == (2,)


@pytest.mark.slow
@pytest.mark.skipif(importlib.util.find_spec("gymnasium_robotics") is None,
                    reason="gymnasium-robotics is not installed (pip install -e '.[robotics]')")
def test_gymnasium_robotics_fetch_reach_trains_through_ebrl_up(tmp_path):
    """FetchReach's Dict (observation, achieved_goal, desired_goal) as it is, named "gymnasium_robotics:..."."""
    code, out, _ = helpers.run_collecting_stats(
        tmp_path / "runs", "configs/quickstart.toml", "run.iterations=2",
        'env.id="gymnasium_robotics:FetchReach-v4"', "sim.envs_per_group=2", "train.batch_size=64",
        run="fetch", timeout=300)
    assert code == 0, out
    policy = ebrl.load_policy(next((tmp_path / "runs").glob("fetch-*")))
    assert [f.name for f in policy.layout.fields] == ["achieved_goal", "desired_goal", "observation"]
    env = gym.make("gymnasium_robotics:FetchReach-v4")
    obs, _ = env.reset(seed=0)
    assert policy.predict(obs)[0].shape == (4,)
    env.close()
