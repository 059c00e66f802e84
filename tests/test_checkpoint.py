"""Training checkpoints: a round trip restores policy, optimizer, random state and version; writes are atomic."""

import dataclasses
import os
import shutil
from types import SimpleNamespace

import numpy as np
import pytest
import torch

import ebrl.policies.checkpoint as policy_checkpoint
from ebrl.algos import checkpoint
from ebrl.algos.ppo import PPO
from ebrl.config import PolicySection
from ebrl.envs import ObsLayout
from ebrl.policies import make_policy, state_arrays

POLICY = PolicySection(kind="mlp", chunk=2, hidden=[8], init_log_std=-0.5, channels=[8], embed_dim=8,
                       denoise_steps=2, checkpoint="")
ALGO = SimpleNamespace(clip=0.2, epochs=1, minibatches=1, ent_coef=0.0, vf_coef=0.5, max_grad_norm=0.5)


def trained(seed=0, steps=3):
    torch.manual_seed(seed)
    model = make_policy(POLICY, ObsLayout.vector(3), 1)
    ppo = PPO(model, ALGO, lr=1e-2, seed=seed)
    for _ in range(steps):  # give Adam some state
        loss = model.evaluate(torch.randn(4, 3), torch.randn(4, 2, 1), torch.zeros(4, 0))[0].sum()
        ppo.optimizer.zero_grad()
        loss.backward()
        ppo.optimizer.step()
    return model, ppo


def test_round_trip_restores_everything(tmp_path):
    model, ppo = trained()
    torch.randperm(5, generator=ppo.generator)  # move the generator on
    path = checkpoint.save(tmp_path, model, ppo.optimizer, 7, {"ppo": ppo.generator})
    assert checkpoint.latest(tmp_path) == path and path.name == "v00000007"
    expected_perm = torch.randperm(10, generator=ppo.generator)
    expected_global = torch.rand(3)
    expected_opt = {k: v.clone() for k, v in ppo.optimizer.state_dict()["state"][0].items()}

    fresh, fresh_ppo = trained(seed=1, steps=1)
    restored = checkpoint.restore(path, fresh, fresh_ppo.optimizer, {"ppo": fresh_ppo.generator})
    assert restored.version == 7
    for name, value in state_arrays(model).items():
        np.testing.assert_array_equal(state_arrays(fresh)[name], value)
    for key, value in fresh_ppo.optimizer.state_dict()["state"][0].items():
        torch.testing.assert_close(value, expected_opt[key])
    assert torch.equal(torch.randperm(10, generator=fresh_ppo.generator), expected_perm)
    assert torch.equal(torch.rand(3), expected_global)


def test_a_new_run_makes_its_optimizer_only_when_it_first_needs_it(tmp_path):
    """torch's first optimizer imports torch._dynamo (most of a second of CPU): a new run's train makes it after
    publishing its first weights. A restore makes it at once when there is a checkpoint to load into it."""
    torch.manual_seed(0)
    model = make_policy(POLICY, ObsLayout.vector(3), 1)
    ppo = PPO(model, ALGO, lr=1e-2)
    assert checkpoint.restore_latest(tmp_path, model, lambda: ppo.optimizer, {"ppo": ppo.generator}) is None
    assert ppo._optimizer is None  # nothing to restore: still not made
    ppo.prepare()
    assert isinstance(ppo._optimizer, torch.optim.Adam) and ppo.optimizer is ppo._optimizer

    trained_model, trained_ppo = trained()
    checkpoint.save(tmp_path, trained_model, trained_ppo.optimizer, 3, {"ppo": trained_ppo.generator})
    other = PPO(model, ALGO, lr=1e-2)
    restored = checkpoint.restore_latest(tmp_path, model, lambda: other.optimizer, {"ppo": other.generator})
    assert restored.version == 3 and other._optimizer is not None
    expected = trained_ppo.optimizer.state_dict()["state"][0]
    for key, value in other.optimizer.state_dict()["state"][0].items():
        torch.testing.assert_close(value, expected[key])


def test_latest_always_names_a_complete_checkpoint_and_old_ones_go(tmp_path):
    model, ppo = trained()
    for version in (10, 20, 30):
        checkpoint.save(tmp_path, model, ppo.optimizer, version, {})
    root = checkpoint.checkpoint_dir(tmp_path)
    assert sorted(p.name for p in root.iterdir() if p.is_dir()) == ["v00000020", "v00000030"]
    (root / "v00000040.tmp").mkdir()  # a crash in the middle of writing v40
    (root / "v00000040.tmp" / "policy.safetensors").write_bytes(b"half")
    assert checkpoint.latest(tmp_path).name == "v00000030"
    assert checkpoint.latest(tmp_path / "nothing") is None


def test_a_checkpoint_of_another_policy_is_refused(tmp_path):
    model, ppo = trained()
    path = checkpoint.save(tmp_path, model, ppo.optimizer, 1, {})
    other = make_policy(dataclasses.replace(POLICY, hidden=[16]), ObsLayout.vector(3), 1)
    with pytest.raises(ValueError, match="shape"):
        checkpoint.restore(path, other, PPO(other, ALGO, lr=1e-2).optimizer, {})


# --- durability: a crash at any point of a write, unreadable checkpoints, stale leftovers ----------------------


class Crash(BaseException):
    """A kill at this point of a write: nothing after it runs (no ``except Exception`` handler catches it)."""


class CrashAt:
    """Counts the steps of a checkpoint write (every file write, fsync, rename and delete) and kills it at step
    ``at``: before the step, or, ``torn``, with a data file half written."""

    def __init__(self, monkeypatch, at: int = 0, torn: bool = False):
        self.at, self.torn, self.steps = at, torn, []
        for owner, name in ((os, "replace"), (os, "fsync"), (shutil, "rmtree"), (checkpoint, "save_file"),
                            (policy_checkpoint, "save_file")):
            monkeypatch.setattr(owner, name, self.step(name, getattr(owner, name)))

    def step(self, name, real):
        def wrapped(*args, **kw):
            self.steps.append(name)
            if len(self.steps) == self.at:
                if self.torn and name == "save_file":  # killed in the middle of writing the file
                    real(*args, **kw)
                    path = args[1]
                    with open(path, "r+b") as fh:
                        fh.truncate(max(1, os.path.getsize(path) // 2))
                raise Crash(f"killed at step {self.at} ({name})")
            return real(*args, **kw)
        return wrapped


def weights_of(model) -> dict[str, np.ndarray]:
    return {k: v.copy() for k, v in state_arrays(model).items()}


def more_trained(model, weights, version):
    """Other weights for ``version`` (in ``weights``)."""
    with torch.no_grad():
        for p in model.parameters():
            p.add_(0.1)
    weights[version] = weights_of(model)


def saved_run(tmp_path, versions=(10, 20)):
    """A run directory with a checkpoint of each version, each of other weights; their weights by version."""
    model, ppo = trained()
    weights = {}
    for version in versions:
        more_trained(model, weights, version)
        checkpoint.save(tmp_path, model, ppo.optimizer, version, {"ppo": ppo.generator})
    return model, ppo, weights


def restore_fresh(run_dir):
    model, ppo = trained(seed=5, steps=1)
    restored = checkpoint.restore_latest(run_dir, model, ppo.optimizer, {"ppo": ppo.generator})
    return restored, weights_of(model)


def assert_weights(actual, expected):
    assert actual.keys() == expected.keys()
    for name, value in expected.items():
        np.testing.assert_array_equal(actual[name], value)


@pytest.mark.parametrize("torn", [False, True], ids=["before-step", "torn-write"])
def test_a_crash_at_any_step_of_a_write_leaves_a_readable_checkpoint_and_versions_go_on(tmp_path, monkeypatch, torn):
    """kill -9 of train during a checkpoint write, then a restart: at every step of writing v30 (with v10 and
    v20 on disk, so pruning v10 is a step too) the restore finds v20 or v30 whole, with exactly its weights, and
    the next save works and leaves no leftovers."""
    model, ppo, weights = saved_run(tmp_path / "count")
    with monkeypatch.context() as patch:
        steps = CrashAt(patch).steps  # counts only
        checkpoint.save(tmp_path / "count", model, ppo.optimizer, 30, {"ppo": ppo.generator})
    assert steps.count("replace") == 4 and steps.count("rmtree") == 1 and steps.count("fsync") >= 7, steps
    renames = [i + 1 for i, step in enumerate(steps) if step == "replace"]  # policy file, v30.tmp, latest, v10
    dir_renamed, pointer_renamed = renames[1], renames[2]  # v30 is whole, then counts (latest names it)
    for at in range(1, len(steps) + 1):
        run_dir = tmp_path / f"crash{at}"
        model, ppo, weights = saved_run(run_dir)
        more_trained(model, weights, 30)
        with monkeypatch.context() as patch, pytest.raises(Crash):
            CrashAt(patch, at, torn)
            checkpoint.save(run_dir, model, ppo.optimizer, 30, {"ppo": ppo.generator})

        restored, restored_weights = restore_fresh(run_dir)
        assert restored is not None, (at, steps[at - 1])
        assert restored.version == (30 if at > pointer_renamed else 20), (at, steps[at - 1])
        assert checkpoint.latest(run_dir) == restored.path and not restored.skipped
        assert_weights(restored_weights, weights[restored.version])
        assert restored.newest == (30 if at > dir_renamed else 20)  # a resumed train goes on past it
        more_trained(model, weights, 40)
        checkpoint.save(run_dir, model, ppo.optimizer, 40, {})  # the next save after the restart works...
        root = checkpoint.checkpoint_dir(run_dir)
        kept = "v00000030" if at > dir_renamed else "v00000020"  # the newest whole one before it
        assert sorted(p.name for p in root.iterdir()) == ["latest", kept, "v00000040"]
        assert_weights(restore_fresh(run_dir)[1], weights[40])  # ... and leaves nothing stale


DAMAGE = {  # what a crash, a full disk or a bad block can leave of a checkpoint's files
    "truncated policy": ("policy.safetensors", lambda b: b[:len(b) // 2]),
    "truncated train state": ("train.safetensors", lambda b: b[:len(b) // 2]),
    "empty train state": ("train.safetensors", lambda b: b""),
    "garbage after the policy": ("policy.safetensors", lambda b: b + b"\x00garbage"),
    "missing policy": ("policy.safetensors", None),
    "missing state.json": ("state.json", None),
    "torn state.json": ("state.json", lambda b: b'{"version": 20, "param_'),
    "state.json not an object": ("state.json", lambda b: b"[20]"),
    "state.json of another version": ("state.json", lambda b: b.replace(b'"version": 20', b'"version": 10')),
}


@pytest.mark.parametrize("damage", DAMAGE)
def test_an_unreadable_newest_checkpoint_is_skipped_and_the_previous_one_restored(tmp_path, damage, caplog):
    _, _, weights = saved_run(tmp_path)
    newest = checkpoint.checkpoint_dir(tmp_path) / "v00000020"
    name, change = DAMAGE[damage]
    if change is None:
        (newest / name).unlink()
    else:
        (newest / name).write_bytes(change((newest / name).read_bytes()))
    restored, restored_weights = restore_fresh(tmp_path)
    assert restored.version == 10 and restored.path.name == "v00000010"
    assert_weights(restored_weights, weights[10])
    assert [p.name for p, _ in restored.skipped] == ["v00000020"] and restored.newest == 20
    assert f"checkpoint {newest} skipped: " in caplog.text
    assert checkpoint.latest(tmp_path).name == "v00000010"


def test_a_dangling_or_garbage_latest_pointer_falls_back_to_the_newest_directory(tmp_path):
    _, _, weights = saved_run(tmp_path)
    pointer = checkpoint.checkpoint_dir(tmp_path) / "latest"
    for content in (b"v00000099\n", b"\xff\xfe garbage \x00", b"", b"../../../etc\n"):
        pointer.write_bytes(content)
        restored, restored_weights = restore_fresh(tmp_path)
        assert restored.version == 20 and not restored.skipped
        assert_weights(restored_weights, weights[20])
    pointer.unlink()
    assert checkpoint.latest(tmp_path).name == "v00000020"
    for name in ("v00000010", "v00000020"):  # nothing readable at all
        (checkpoint.checkpoint_dir(tmp_path) / name / "train.safetensors").write_bytes(b"junk")
    assert restore_fresh(tmp_path)[0] is None and checkpoint.latest(tmp_path) is None


def test_a_checkpoint_that_does_not_fit_is_an_error_not_skipped(tmp_path):
    saved_run(tmp_path)
    other = make_policy(dataclasses.replace(POLICY, hidden=[16]), ObsLayout.vector(3), 1)
    with pytest.raises(ValueError, match="shape"):
        checkpoint.restore_latest(tmp_path, other, PPO(other, ALGO, lr=1e-2).optimizer, {})


def test_stale_leftovers_are_removed_at_save_and_at_start_and_unreadable_ones_are_not_kept(tmp_path):
    model, ppo, _ = saved_run(tmp_path)
    root = checkpoint.checkpoint_dir(tmp_path)
    (root / "v00000030.tmp").mkdir()
    (root / "v00000030.tmp" / "policy.safetensors").write_bytes(b"half")
    (root / "latest.tmp").write_text("v000")
    (root / "v00000005.old.tmp").mkdir()
    assert sorted(p.name for p in checkpoint.remove_stale(tmp_path)) == ["latest.tmp", "v00000005.old.tmp",
                                                                        "v00000030.tmp"]
    (root / "v00000030.tmp").mkdir()
    (root / "v00000020" / "train.safetensors").write_bytes(b"")  # v20 unreadable: v10 is the one to keep
    checkpoint.save(tmp_path, model, ppo.optimizer, 30, {})
    assert sorted(p.name for p in root.iterdir()) == ["latest", "v00000010", "v00000030"]
