"""policy.kind as a registry (issue 55): every registered kind resolves and its facts are its class's, a user's
own ChunkPolicy subclass by "module:Class" is checked before a run starts, trains through a real `ebrl up`, and
its checkpoint rebuilds it with `ebrl.load_policy`; docs/policies.md shows the example that run uses."""

from __future__ import annotations

import dataclasses
import importlib.util
import json
import subprocess
import sys
from pathlib import Path

import numpy as np
import pytest
import torch

import ebrl
from ebrl import sizes
from ebrl.config import Config, ConfigError, PolicySection, load
from ebrl.envs import EnvSpec, ObsField, ObsLayout, describe
from ebrl.policies import make_policy, policy_class, save_checkpoint
from ebrl.policies.base import ChunkPolicy
from ebrl.policies.checkpoint import portable_metadata, read_metadata
from ebrl.policies.flow import FlowPolicy
from ebrl.policies.portable import PolicyFileError, from_metadata
from ebrl.policies.registry import KINDS, KNOWN, known_facts, preflight, trained_by_problem
from ebrl.policies.squashed import ChunkSquashedMLP
from ebrl.prepare import preflight as run_preflight
from helpers import StatsWatcher, up

ROOT = Path(__file__).resolve().parent.parent
EXAMPLES = ROOT / "examples"
USER_KIND = "my_policy:ResidualPolicy"  # examples/my_policy.py
STATE = ObsLayout.vector(6)
VISION = ObsLayout((ObsField("image", "image", (3, 16, 16)), ObsField("proprio", "vector", (4,))))
BOUNDS = (np.full(2, -1.0), np.full(2, 1.0))
A = 2


def policy_cfg(kind: str, **changes) -> PolicySection:
    return dataclasses.replace(PolicySection(kind=kind, chunk=3, hidden=[8], channels=[4], embed_dim=8,
                                             denoise_steps=2), **changes)


@pytest.fixture
def examples(monkeypatch):
    """examples/ importable, as a user's package is (installed, or on PYTHONPATH)."""
    monkeypatch.syspath_prepend(str(EXAMPLES))


# --- a user's kinds the tests name as "test_policy_registry:..." (tests/ is on sys.path) -----------------

class MySquashed(ChunkSquashedMLP):
    """A user's SAC actor: it inherits the squashed kind's facts (trained by sac, needs the bounds)."""


class MyFlow(FlowPolicy):
    """A user's flow head: its latents are the chunk's, which the simulator must know without building it."""


class NoFromConfig(ChunkPolicy):
    latent_shape = (0,)


# --- the registry ---------------------------------------------------------------------------------------

@pytest.mark.parametrize("kind", [k for k in KINDS if k != "vla"])
def test_every_registered_kind_resolves_to_its_class_and_builds(kind):
    cls = policy_class(kind)
    assert issubclass(cls, ChunkPolicy) and cls.kind == kind and KINDS[kind].endswith(":" + cls.__name__)
    model = make_policy(policy_cfg(kind), VISION if kind == "cnn" else STATE, A, BOUNDS)
    assert type(model) is cls and model.kind == kind and model.options == {}
    actions, logprobs, values, latents = model.act(np.zeros((4, model.layout.size), np.float32))
    assert actions.shape == (4, 3, A) and latents.shape == (4, *model.latent_shape)


def test_the_vla_kind_is_reserved_for_its_module():
    if importlib.util.find_spec("ebrl.policies.vla") is None:  # written beside this registry: until it exists
        with pytest.raises(ValueError, match="policy.kind = 'vla': cannot load ebrl.policies.vla:VLAPolicy"):
            policy_class("vla")
    else:
        assert policy_class("vla").__name__ == "VLAPolicy" and issubclass(policy_class("vla"), ChunkPolicy)


@pytest.mark.parametrize("kind", list(KNOWN))
def test_what_the_registry_knows_without_importing_is_each_classs_own_fact(kind):
    """KNOWN copies a registered kind's facts for processes that build no policy: each copy is its class's."""
    cls = policy_class(kind)
    known = KNOWN[kind]
    assert known_facts(cls, known.chunk_latents) == known
    for chunk in (1, 3):
        cfg = policy_cfg(kind, chunk=chunk)
        model = make_policy(cfg, VISION if kind == "cnn" else STATE, A, BOUNDS)
        shape = known.latent_shape(chunk, A)
        assert tuple(cls.latent_shape_of(cfg, A)) == shape == sizes.latent_shape(cfg, A)
        assert tuple(model.latent_shape) == shape or np.prod(model.latent_shape) == 0 == np.prod(shape)


def test_a_users_kind_is_asked_its_facts_by_its_class():
    assert sizes.latent_shape(policy_cfg("test_policy_registry:MyFlow"), A) == (3, A)
    assert sizes.latent_shape(policy_cfg("test_policy_registry:MySquashed"), A) == (0,)
    with pytest.raises(ValueError, match="needs the env's action bounds"):
        make_policy(policy_cfg("test_policy_registry:MySquashed"), STATE, A)
    assert make_policy(policy_cfg("test_policy_registry:MySquashed"), STATE, A, BOUNDS).kind == \
        "test_policy_registry:MySquashed"


def test_loading_a_config_imports_no_policy_and_no_torch():
    """Every service checks policy.kind as it reads the config, the simulator too: by name, importing nothing."""
    code = ("import sys, ebrl.config as c, ebrl.sizes as s\n"
            "cfg = c.load('configs/quickstart.toml', ['policy.kind=\"flow\"', 'policy.backbone=\"transformer\"'])\n"
            "print(s.latent_shape(cfg.policy, 2), 'torch' in sys.modules)")
    out = subprocess.run([sys.executable, "-c", code], capture_output=True, text=True, timeout=60, check=True, cwd=ROOT)
    assert out.stdout.strip() == "(4, 2) False"


# --- refusals, each naming the field ----------------------------------------------------------------------

def test_a_typod_kind_is_a_config_error_naming_the_field_and_the_choices():
    with pytest.raises(ConfigError, match=r"policy.kind = 'mpl': not one of mlp, cnn, flow, squashed, vla, nor your "
                                          r"own as \"pkg.module:Class\" .*\(did you mean 'mlp'\?\)"):
        load("quickstart", ["policy.kind=mpl"])
    with pytest.raises(ConfigError, match="policy.kind = ':Mine'"):
        load("quickstart", ["policy.kind=:Mine"])


def test_a_module_class_that_is_not_a_policy_is_refused_before_the_run_starts():
    cfg = load("quickstart", ["policy.kind=ebrl.policies.nets:ObsEncoder"])  # the config imports nothing...
    problem = run_preflight(cfg, ("sim",))  # ... the launcher's preflight does, before any service starts
    assert problem == ("policy.kind = 'ebrl.policies.nets:ObsEncoder': ebrl.policies.nets:ObsEncoder is not an "
                       "ebrl.policies.base.ChunkPolicy subclass (the module must be importable by the run's "
                       "processes: installed, or on PYTHONPATH)")
    missing = run_preflight(load("quickstart", ["policy.kind=no_such_pkg.policies:Mine"]), ("sim",))
    assert "policy.kind = 'no_such_pkg.policies:Mine': cannot load" in missing and "No module named 'no_such_pkg'" in \
        missing and "PYTHONPATH" in missing
    with pytest.raises(NotImplementedError, match="NoFromConfig does not say how to build it from a config: define "
                                                  "the classmethod from_config"):
        make_policy(policy_cfg("test_policy_registry:NoFromConfig"), STATE, A)


def test_an_algorithm_trains_only_the_kinds_that_say_so():
    with pytest.raises(ConfigError, match="algo.name = 'sac' with policy.kind = 'mlp': that kind is trained by "
                                          "grpo, ppo .*use policy.kind = 'squashed'"):
        load("sac_pendulum", ["policy.kind=mlp"])
    with pytest.raises(ConfigError, match="algo.name = 'ppo' with policy.kind = 'squashed': that kind is trained by "
                                          "sac"):
        load("sac_pendulum", ["algo.name=ppo"])
    # a user's kind inherits its facts; the launcher checks them (the config cannot without importing it)
    assert preflight(policy_cfg("test_policy_registry:MySquashed"), "sac") is None
    assert "that kind is trained by sac" in preflight(policy_cfg("test_policy_registry:MySquashed"), "ppo")
    assert "policy.backbone = 'transformer'" in preflight(
        policy_cfg("test_policy_registry:MySquashed", backbone="transformer"), "sac")
    # and a learner refuses a built one (a config that skipped the check): ppo's, sac's
    squashed = make_policy(policy_cfg("squashed"), STATE, A, BOUNDS)
    assert "algo.name = 'ppo' with policy.kind = 'squashed'" in trained_by_problem(squashed, "ppo")
    assert trained_by_problem(squashed, "sac") is None and trained_by_problem(squashed, "user_algos:Mine") is None


# --- checkpoints ------------------------------------------------------------------------------------------

def test_a_users_checkpoint_records_its_kind_and_options_and_rebuilds_without_the_config(tmp_path, examples):
    info = describe(EnvSpec.from_config(Config().env))
    cfg = policy_cfg(USER_KIND, options={"width": 16})
    torch.manual_seed(0)
    model = make_policy(cfg, info.layout, info.action_dim)
    path = tmp_path / "policy.safetensors"
    save_checkpoint(model, str(path), {"version": "1", **portable_metadata(cfg, Config().env, info)})
    metadata = read_metadata(str(path))
    section = json.loads(metadata["policy"])
    assert metadata["kind"] == section["kind"] == USER_KIND
    assert section["options"] == {"width": 16, "blocks": 2}  # the model's options: the defaults it filled in
    policy = ebrl.load_policy(path)
    obs = np.random.default_rng(0).normal(size=(3, info.layout.size)).astype(np.float32)
    assert type(policy.model).__name__ == "ResidualPolicy" and policy.kind == USER_KIND
    np.testing.assert_allclose(policy.predict_chunk(obs), model.predict_chunk(obs), atol=1e-6)
    gone = {**metadata, "policy": json.dumps({**section, "kind": "no_such_pkg.policies:Mine"})}
    with pytest.raises(PolicyFileError, match="cannot rebuild its policy: policy.kind = 'no_such_pkg.policies:Mine'"):
        from_metadata(gone, source=str(path))


# --- the docs' example, through `ebrl up` -----------------------------------------------------------------

COMMAND = f"PYTHONPATH=examples ebrl up configs/quickstart.toml --set policy.kind={USER_KIND}"


def test_the_docs_show_the_example_whole_and_the_command_that_trains_it():
    page = (ROOT / "docs" / "policies.md").read_text()
    assert (EXAMPLES / "my_policy.py").read_text() in page
    assert COMMAND in page and COMMAND in (EXAMPLES / "my_policy.py").read_text()


def test_a_users_policy_class_trains_through_ebrl_up_and_its_checkpoint_loads_and_predicts(tmp_path, monkeypatch,
                                                                                          examples):
    """The docs' command (docs/policies.md), for 3 iterations: the services import the user's module from
    PYTHONPATH, as they do a user's module:EnvId."""
    monkeypatch.setenv("PYTHONPATH", str(EXAMPLES))
    with up(tmp_path, "configs/quickstart.toml", f"policy.kind={USER_KIND}", "policy.options.width=32",
            "run.iterations=3", "train.batch_size=256", name="user-policy") as run, StatsWatcher(run) as stats:
        code = run.wait(240)
    assert code == 0, run.output
    assert stats.latest("train/0", "train/policy_version") == 3
    assert np.isfinite(stats.latest("train/0", "train/policy_loss"))
    policy = ebrl.load_policy(run.run_dir)
    assert policy.kind == USER_KIND and policy.version == 3
    assert policy.policy_config["options"] == {"width": 32, "blocks": 2}
    assert policy.model.torso[0].out_features == 32
    env = policy.make_env()
    obs, _ = env.reset(seed=0)
    action, _ = policy.predict(obs)
    assert action.shape == env.action_space.shape and env.action_space.contains(action.astype(np.float32))
    env.close()
