"""Policy kinds behind one interface: shapes, gen/train log-prob agreement, learning signal, denoising steps,
instruction tokens, safetensors checkpoints."""

import dataclasses
import os

import numpy as np
import pytest
import torch

from ebrl.config import PolicySection
from ebrl.envs.obs import ObsField, ObsLayout, tokenize
from ebrl.policies import load_arrays, load_checkpoint, make_policy, save_checkpoint, state_arrays

STATE = ObsLayout.vector(6)
VISION = ObsLayout((ObsField("image", "image", (3, 32, 32)), ObsField("proprio", "vector", (5,)),
                    ObsField("instruction", "tokens", (16,))))
ACTION_DIM, CHUNK, BATCH = 2, 3, 5
CASES = {"mlp": ("mlp", STATE), "cnn": ("cnn", VISION), "flow-vision": ("flow", VISION), "flow-state": ("flow", STATE),
         "flow-transformer": ("flow", VISION)}
CASE_CHANGES = {"flow-transformer": dict(backbone="transformer", width=16, depth=2, heads=2, patch=8)}


def policy_cfg(kind: str, **changes) -> PolicySection:
    return dataclasses.replace(PolicySection(kind=kind, chunk=CHUNK, hidden=[16], channels=[4, 8], embed_dim=8,
                                             denoise_steps=3), **changes)


def observations(layout: ObsLayout, batch: int = BATCH, seed: int = 0,
                 instruction: str = "pick up the red cube") -> np.ndarray:
    rng = np.random.default_rng(seed)

    def one() -> np.ndarray:
        values = {}
        for f in layout.fields:
            if f.kind == "image":
                values[f.name] = rng.uniform(0, 1, f.shape)
            elif f.kind == "tokens":
                values[f.name] = tokenize(instruction, f.size)
            else:
                values[f.name] = rng.normal(size=f.shape)
        return layout.pack(values)

    return np.stack([one() for _ in range(batch)])


def build(case: str, seed: int = 0, **changes):
    kind, layout = CASES[case]
    changes = {**CASE_CHANGES.get(case, {}), **changes}
    torch.manual_seed(seed)
    return make_policy(policy_cfg(kind, **changes), layout, ACTION_DIM), layout


@pytest.mark.parametrize("case", CASES)
def test_act_returns_chunks_logprobs_values_and_latents(case):
    model, layout = build(case)
    actions, logprobs, values, latents = model.act(observations(layout))
    assert model.chunk == CHUNK and model.action_dim == ACTION_DIM
    assert actions.shape == (BATCH, CHUNK, ACTION_DIM) and logprobs.shape == values.shape == (BATCH,)
    assert latents.shape == (BATCH, *model.latent_shape)
    assert model.latent_shape == ((CHUNK, ACTION_DIM) if model.kind == "flow" else (0,))
    for out in (actions, logprobs, values, latents):
        assert isinstance(out, np.ndarray) and out.dtype == np.float32
    assert np.isfinite(logprobs).all() and np.isfinite(actions).all()
    assert model.value(torch.as_tensor(observations(layout))).shape == (BATCH,)


def test_image_observations_may_arrive_with_their_shape():
    torch.manual_seed(0)
    layout = ObsLayout.for_shape((3, 36, 36))  # an image-only env; odd size for the conv stack
    model = make_policy(policy_cfg("cnn"), layout, ACTION_DIM)
    obs = np.random.default_rng(0).uniform(0, 1, (BATCH, 3, 36, 36)).astype(np.float32)
    actions, _, _, _ = model.act(obs)
    assert actions.shape == (BATCH, CHUNK, ACTION_DIM)


@pytest.mark.parametrize("case", CASES)
def test_log_prob_is_the_same_in_gen_and_train(case):
    gen_model, layout = build(case, seed=1)
    train_model, _ = build(case, seed=2)
    load_arrays(train_model, state_arrays(gen_model))  # what a Weights message carries
    obs = observations(layout)
    actions, logprobs, values, latents = gen_model.act(obs)
    lp, entropy, v = train_model.evaluate(torch.as_tensor(obs), torch.as_tensor(actions), torch.as_tensor(latents))
    np.testing.assert_allclose(lp.detach().numpy(), logprobs, rtol=1e-5, atol=1e-5)
    np.testing.assert_allclose(v.detach().numpy(), values, rtol=1e-5, atol=1e-5)
    assert entropy.shape == (BATCH,) and torch.isfinite(entropy).all()


@pytest.mark.parametrize("case", ["mlp", "cnn"])
def test_gaussian_chunks_are_drawn_from_the_policys_distribution(case):
    """``sample`` writes mean + std * eps out by hand (generation's hot path): its draws have the heads'
    mean and standard deviation."""
    model, layout = build(case)
    with torch.no_grad():
        model.log_std.copy_(torch.linspace(-1.0, 0.5, model.log_std.numel()))
    obs = np.repeat(observations(layout, batch=1), 4000, axis=0)
    actions, _, _, _ = model.act(obs)
    d, _ = model.heads(model.flat(obs[:1]))
    flat = actions.reshape(len(obs), -1)
    std = d.stddev[0].detach().numpy()
    np.testing.assert_allclose(flat.mean(0), d.mean[0].detach().numpy(), atol=4 * std.max() / np.sqrt(len(obs)))
    np.testing.assert_allclose(flat.std(0), std, rtol=0.06)


@pytest.mark.parametrize("sign", [1.0, -1.0])
@pytest.mark.parametrize("case", CASES)
def test_a_gradient_step_moves_the_log_prob_with_the_advantage(case, sign):
    model, layout = build(case)
    obs = observations(layout)
    actions, _, _, latents = model.act(obs)
    o, a, z = torch.as_tensor(obs), torch.as_tensor(actions), torch.as_tensor(latents)
    before = model.evaluate(o, a, z)[0]
    opt = torch.optim.SGD(model.parameters(), lr=1e-3)
    opt.zero_grad()
    (-(before * sign).mean()).backward()
    if hasattr(model, "encoder"):  # the image / state / instruction encoder learns from the policy loss
        assert all(p.grad is not None and p.grad.abs().sum() > 0 for p in model.encoder.parameters())
    if hasattr(model, "velocity"):  # gradients flow through the whole denoising chain
        assert all(p.grad.abs().sum() > 0 for p in model.velocity.parameters())
    opt.step()
    after = model.evaluate(o, a, z)[0]
    assert sign * (after - before).mean().item() > 0


def test_denoise_steps_change_the_cost_not_the_interface():
    obs = observations(VISION)
    shapes, calls = {}, {}
    for steps in (1, 2, 8):
        model, _ = build("flow-vision", denoise_steps=steps)
        shapes[steps] = {name: tuple(t.shape) for name, t in model.state_dict().items()}
        count = [0]
        model.velocity.register_forward_hook(lambda *_: count.__setitem__(0, count[0] + 1))
        actions, logprobs, values, latents = model.act(obs)
        assert actions.shape == (BATCH, CHUNK, ACTION_DIM) and latents.shape == (BATCH, CHUNK, ACTION_DIM)
        calls[steps] = count[0]
        model.evaluate(torch.as_tensor(obs), torch.as_tensor(actions), torch.as_tensor(latents))
        assert count[0] == 2 * steps  # one velocity-net call per step, in generation and in training
    assert shapes[1] == shapes[2] == shapes[8]
    assert calls == {1: 1, 2: 2, 8: 8}
    one_step, _ = build("flow-vision", denoise_steps=1)
    eight_steps, _ = build("flow-vision", seed=5, denoise_steps=8)
    load_arrays(one_step, state_arrays(eight_steps))  # weights move between N freely


def test_flow_evaluate_refuses_latents_of_the_wrong_shape():
    model, layout = build("flow-state")
    obs = torch.as_tensor(observations(layout))
    with pytest.raises(ValueError, match="latents"):
        model.evaluate(obs, torch.zeros(BATCH, CHUNK, ACTION_DIM), torch.zeros(BATCH, 0))


def test_cnn_needs_an_image_field():
    with pytest.raises(ValueError, match="image"):
        make_policy(policy_cfg("cnn"), STATE, ACTION_DIM)


def test_instruction_tokens_change_the_cnn_output():
    model, layout = build("cnn")
    obs_a = observations(layout, instruction="pick up the red cube")
    obs_b = observations(layout, instruction="open the top drawer")  # same image and proprioception
    actions = torch.zeros(BATCH, CHUNK, ACTION_DIM)
    latents = torch.zeros(BATCH, 0)
    lp_a, _, v_a = model.evaluate(torch.as_tensor(obs_a), actions, latents)
    lp_b, _, v_b = model.evaluate(torch.as_tensor(obs_b), actions, latents)
    assert (v_a - v_b).abs().min() > 1e-6 and (lp_a - lp_b).abs().min() > 1e-9


@pytest.mark.parametrize("case", CASES)
def test_checkpoint_round_trip_gives_identical_actions(case, tmp_path):
    model, layout = build(case, seed=3)
    path = str(tmp_path / "policy.safetensors")
    save_checkpoint(model, path, {"step": "7"})
    assert os.listdir(tmp_path) == ["policy.safetensors"]  # no temp file left behind
    kind = CASES[case][0]
    torch.manual_seed(4)  # other initial weights, replaced by the checkpoint's
    fresh = make_policy(policy_cfg(kind, checkpoint=path, **CASE_CHANGES.get(case, {})), layout, ACTION_DIM)
    obs = observations(layout)
    torch.manual_seed(9)
    expected = model.act(obs)
    torch.manual_seed(9)
    got = fresh.act(obs)
    for e, g in zip(expected, got):
        np.testing.assert_array_equal(e, g)
    metadata = load_checkpoint(fresh, path)
    assert metadata["step"] == "7" and metadata["kind"] == kind and metadata["chunk"] == str(CHUNK)


def test_checkpoint_with_other_shapes_names_the_tensor(tmp_path):
    path = str(tmp_path / "policy.safetensors")
    save_checkpoint(build("cnn", hidden=[16])[0], path, {})
    with pytest.raises(ValueError, match=r"trunk\.0\.weight has shape"):
        load_checkpoint(build("cnn", hidden=[8])[0], path)


def test_checkpoint_of_another_policy_or_task_is_refused(tmp_path):
    path = str(tmp_path / "policy.safetensors")
    save_checkpoint(build("mlp")[0], path, {})
    with pytest.raises(ValueError, match="kind is 'mlp', the model's is 'flow'"):
        load_checkpoint(build("flow-state")[0], path)
    with pytest.raises(ValueError, match="chunk"):
        load_checkpoint(build("mlp", chunk=CHUNK + 1)[0], path)
    with pytest.raises(ValueError, match="layout"):
        load_checkpoint(make_policy(policy_cfg("mlp"), ObsLayout.vector(7), ACTION_DIM), path)


def test_missing_or_unreadable_checkpoint_is_a_clear_error(tmp_path):
    with pytest.raises(FileNotFoundError, match="no such file"):
        make_policy(policy_cfg("mlp", checkpoint=str(tmp_path / "absent.safetensors")), STATE, ACTION_DIM)
    junk = tmp_path / "junk.safetensors"
    junk.write_bytes(b"not a checkpoint")
    with pytest.raises(ValueError, match="safetensors"):
        load_checkpoint(build("mlp")[0], str(junk))


def test_obs_normalizer_keeps_running_statistics_of_the_vector_fields_only():
    from ebrl.policies import ObsNormalizer

    norm = ObsNormalizer(VISION)
    obs = torch.as_tensor(observations(VISION, batch=40), dtype=torch.float32)
    torch.testing.assert_close(norm(obs), obs)  # before the first batch: the identity (in the clip range)
    parts = [obs[:13] * 3 + 5, obs[13:] * 3 + 5]  # two batches, folded in one after the other
    for part in parts:
        norm.merge(norm.sums(part))
    whole = torch.cat(parts).double()
    proprio = slice(3 * 32 * 32, 3 * 32 * 32 + 5)
    torch.testing.assert_close(norm.mean[proprio].double(), whole[:, proprio].mean(0), rtol=1e-5, atol=1e-5)
    torch.testing.assert_close(norm.var[proprio].double(), whole[:, proprio].var(0, unbiased=False),
                               rtol=1e-4, atol=1e-5)
    assert norm.count.item() == 40
    norm.merge(norm.sums(whole[:0]))  # a rank without data this update adds nothing
    assert norm.count.item() == 40
    out = norm(whole.float())
    assert abs(out[:, proprio].mean().item()) < 1e-4 and abs(out[:, proprio].std().item() - 1) < 0.05
    torch.testing.assert_close(out[:, :3 * 32 * 32], whole.float()[:, :3 * 32 * 32])  # image unchanged
    torch.testing.assert_close(out[:, -16:], whole.float()[:, -16:])  # instruction tokens unchanged
    far = whole.float()[:1].clone()
    far[0, proprio] = 1e6
    assert norm(far)[0, proprio].max().item() == norm.clip


@pytest.mark.parametrize("case", list(CASES))
def test_normalize_obs_statistics_travel_with_the_weights(case):
    from ebrl.policies import ObsNormalizer

    policy, layout = build(case, normalize_obs=True)
    obs = observations(layout, batch=16)
    vector = ObsNormalizer(layout).mask.numpy()
    obs[:, vector] = obs[:, vector] * 4 + 2  # far from standard: the statistics will matter
    before = policy.value(torch.as_tensor(obs, dtype=torch.float32))
    policy.obs_norm.merge(policy.obs_norm.sums(obs))
    after = policy.value(torch.as_tensor(obs, dtype=torch.float32))
    assert not torch.allclose(before, after)  # the statistics change what every head sees
    arrays = state_arrays(policy)
    assert {"obs_norm.mean", "obs_norm.var", "obs_norm.count"} <= set(arrays) and "obs_norm.mask" not in arrays
    other, _ = build(case, seed=1, normalize_obs=True)
    load_arrays(other, arrays)  # what generation does with a Weights message
    torch.testing.assert_close(other.value(torch.as_tensor(obs, dtype=torch.float32)), after)
    plain, _ = build(case)
    with pytest.raises(ValueError, match="obs_norm"):  # a normalising policy's weights need a normalising model
        load_arrays(plain, arrays)


def test_the_transformer_backbone_reads_every_patch_and_the_instruction():
    policy, layout = build("flow-transformer")
    obs = observations(layout, batch=2)
    features = policy.encoder(policy.flat(obs))
    assert features.shape == (2, 16)
    other = observations(layout, batch=2, instruction="open the drawer")
    assert not torch.allclose(policy.encoder(policy.flat(other)), features)  # the words reach the features
    corner = obs.copy()
    corner[:, :3] += 1.0  # three pixels of the top-left patch (the image comes first in the layout)
    assert not torch.allclose(policy.encoder(policy.flat(corner)), features)


def test_the_w3_config_is_a_paper_scale_policy():
    """configs/bench_w3.toml: a flow policy with a transformer backbone of at least 300M parameters (counted
    on the meta device: nothing is allocated)."""
    from pathlib import Path

    from ebrl import config
    from ebrl.envs.obs import INSTRUCTION_TOKENS

    cfg = config.load(str(Path(__file__).resolve().parent.parent / "configs" / "bench_w3.toml"))
    assert cfg.policy.kind == "flow" and cfg.policy.backbone == "transformer" and cfg.policy.denoise_steps >= 8
    size = cfg.env.kwargs["image_size"]
    layout = ObsLayout((ObsField("image", "image", (3, size, size)), ObsField("proprio", "vector", (43,)),
                        ObsField("instruction", "tokens", (INSTRUCTION_TOKENS,))))
    with torch.device("meta"):
        model = make_policy(cfg.policy, layout, 7)
    assert sum(p.numel() for p in model.parameters()) >= 300e6


def test_the_transformer_backbone_checks_its_shape():
    with pytest.raises(ValueError, match="policy.patch = 5 does not divide"):
        build("flow-transformer", patch=5)
