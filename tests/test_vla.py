"""policy.kind = "vla": a transformers vision tower and decoder (tiny, random, real architectures: SigLIP and Llama,
saved with save_pretrained and loaded back through the options) under the flow head; LoRA; PPO through `ebrl up`.

No weights are downloaded: every backbone here is built from a config on this machine.
"""

import json
import shutil
import sys

import numpy as np
import pytest
import torch

pytest.importorskip("transformers", reason="the vla extra: pip install -e '.[vla]'")

from transformers import LlamaConfig, LlamaModel, SiglipVisionConfig, SiglipVisionModel  # noqa: E402

import helpers  # noqa: E402
from ebrl import devices  # noqa: E402
from ebrl.algos.ppo import PPO, Batch  # noqa: E402
from ebrl.config import PolicySection  # noqa: E402
from ebrl.envs.obs import ObsField, ObsLayout, sample_observations  # noqa: E402
from ebrl.policies.vla import VLAPolicy  # noqa: E402
from test_libero import needs_libero  # noqa: E402

LAYOUT = ObsLayout((ObsField("agentview", "image", (3, 48, 48), uint8=True),
                    ObsField("wrist", "image", (3, 48, 48), uint8=True),
                    ObsField("proprio", "vector", (8,)), ObsField("instruction", "tokens", (16,))))
PPO_CFG = type("Algo", (), dict(gamma=0.9, gae_lambda=0.5, clip=0.2, epochs=2, minibatches=2, ent_coef=0.0,
                                vf_coef=0.5, max_grad_norm=0.5))()
CLIP_MEAN, CLIP_STD = [0.481, 0.458, 0.408], [0.269, 0.261, 0.276]


def save_backbones(root, image_size=32):
    """A tiny SigLIP vision tower (with its pooling head, which the policy leaves out) and a tiny Llama decoder,
    random, saved as a user's weights would be; the vision directory has a processor config."""
    torch.manual_seed(0)
    vision = SiglipVisionModel(SiglipVisionConfig(hidden_size=32, intermediate_size=64, num_hidden_layers=2,
                                                  num_attention_heads=2, image_size=image_size, patch_size=8))
    language = LlamaModel(LlamaConfig(vocab_size=4096, hidden_size=32, intermediate_size=64, num_hidden_layers=2,
                                      num_attention_heads=2, num_key_value_heads=1, max_position_embeddings=256))
    vision.save_pretrained(root / "siglip")
    language.save_pretrained(root / "llama")
    (root / "siglip" / "preprocessor_config.json").write_text(json.dumps({"image_mean": CLIP_MEAN,
                                                                          "image_std": CLIP_STD}))
    return root / "siglip", root / "llama"


@pytest.fixture(scope="module")
def backbones(tmp_path_factory):
    return save_backbones(tmp_path_factory.mktemp("weights"))


def policy(backbones, layout=LAYOUT, **options):
    vision, language = backbones
    return VLAPolicy(layout, 7, 4, [32, 32], 2, options={"vision": str(vision), "language": str(language), **options})


def obs(n=3, layout=LAYOUT):
    return torch.as_tensor(sample_observations(layout, n, rng=1), dtype=torch.float32)


def backbone_weights(model):
    """The transformers models' own weights (LoRA's base layers included, its adapters not), by name."""
    return {name: p.detach().clone() for name, p in model.named_parameters()
            if name.startswith(("encoder.vision.", "encoder.language.")) and "lora_" not in name}


def test_loads_the_weights_and_rebuilds_from_its_options_alone(backbones, tmp_path):
    model = policy(backbones)
    saved = SiglipVisionModel.from_pretrained(backbones[0])
    assert torch.equal(model.encoder.vision.embeddings.patch_embedding.weight,
                       saved.embeddings.patch_embedding.weight)  # loaded, not random
    assert not any(".head." in name for name in model.state_dict())  # SigLIP's pooling head is not built
    assert model.options["image_mean"] == CLIP_MEAN and model.options["image_std"] == CLIP_STD
    text = json.dumps(model.options)  # JSON, for the checkpoint's metadata; no path of the weights in it
    assert str(backbones[0]) not in text and str(backbones[1]) not in text
    assert model.options["vision_config"]["model_type"] == "siglip_vision_model"
    rebuilt = VLAPolicy(LAYOUT, 7, 4, [32, 32], 2, options=json.loads(text))  # random init from the configs
    assert {k: v.shape for k, v in rebuilt.state_dict().items()} == {k: v.shape for k, v in model.state_dict().items()}
    assert not torch.equal(rebuilt.encoder.language.layers[0].mlp.up_proj.weight,
                           model.encoder.language.layers[0].mlp.up_proj.weight)
    rebuilt.load_state_dict(model.state_dict())
    o = obs()
    chunk = model.predict_chunk(o.numpy())
    assert chunk.shape == (3, 4, 7) and np.isfinite(chunk).all()
    np.testing.assert_array_equal(rebuilt.predict_chunk(o.numpy()), chunk)
    actions, logp, value, x0 = model.act(o)  # training recomputes the log-prob generation reported
    again, _, v = model.evaluate(o, torch.as_tensor(actions), torch.as_tensor(x0))
    torch.testing.assert_close(again, torch.as_tensor(logp), rtol=1e-4, atol=1e-4)
    torch.testing.assert_close(v, torch.as_tensor(value))


def test_the_vision_tower_of_a_two_tower_siglip_checkpoint_is_read(tmp_path, backbones):
    from transformers import SiglipConfig, SiglipModel

    tower = dict(hidden_size=32, intermediate_size=64, num_hidden_layers=1, num_attention_heads=2)
    both = SiglipModel(SiglipConfig(vision_config={**tower, "image_size": 32, "patch_size": 8},
                                    text_config={**tower, "vocab_size": 100}))
    both.save_pretrained(tmp_path / "siglip-both")
    model = policy((tmp_path / "siglip-both", backbones[1]))
    assert model.options["vision_config"]["model_type"] == "siglip_vision_model"
    assert torch.equal(model.encoder.vision.embeddings.patch_embedding.weight,
                       both.vision_model.embeddings.patch_embedding.weight)


def test_the_images_and_the_instruction_change_the_features(backbones):
    model = policy(backbones)
    o = obs(2)
    parts = LAYOUT.split(o.clone())
    base = model.encoder(o)
    other_image, other_words = o.clone(), o.clone()
    LAYOUT.split(other_image)["wrist"].mul_(0.5)  # views into the flat rows
    LAYOUT.split(other_words)["instruction"][:, 0] = parts["instruction"][:, 0] % 4000 + 1
    for changed in (other_image, other_words):
        assert not torch.allclose(model.encoder(changed), base)


def test_with_lora_only_the_adapters_and_the_head_train_through_ppo(backbones):
    model = policy(backbones, lora={"r": 4, "alpha": 8})
    parts = model.trainable()
    adapters = sum(p.numel() for n, p in model.named_parameters() if "lora_" in n)
    head = sum(p.numel() for n, p in model.named_parameters() if not n.startswith(("encoder.vision.",
                                                                                   "encoder.language.")))
    assert parts == {"lora": adapters, "backbone": 0, "head": head} and adapters > 0
    learner = PPO(model, PPO_CFG, lr=1e-2)
    seen = [p for group in learner.optimizer.param_groups for p in group["params"]]
    assert all(p.requires_grad for p in seen) and sum(p.numel() for p in seen) == adapters + head
    before, lora_before = backbone_weights(model), {n: p.detach().clone() for n, p in model.named_parameters()
                                                    if "lora_B" in n}
    o = obs(8)
    actions, logp, values, x0 = model.act(o)
    batch = Batch(obs=o, actions=torch.as_tensor(actions), latents=torch.as_tensor(x0), logprobs=torch.as_tensor(logp),
                  advantages=torch.randn(8), returns=torch.randn(8), values=torch.as_tensor(values),
                  versions=np.zeros(8, np.int64))
    out = learner.update(batch)
    assert np.isfinite(out["policy_loss"])
    after = backbone_weights(model)
    assert all(torch.equal(before[n], after[n]) for n in before)  # no base weight of either backbone moved
    assert any(not torch.equal(p, lora_before[n]) for n, p in model.named_parameters() if "lora_B" in n)


def test_freeze_keeps_a_backbone_fixed_and_full_fine_tuning_trains_both(backbones):
    full = policy(backbones).trainable()
    frozen = policy(backbones, freeze=["vision"]).trainable()
    assert full["lora"] == frozen["lora"] == 0 and full["head"] == frozen["head"]
    vision = sum(p.numel() for n, p in policy(backbones).named_parameters() if n.startswith("encoder.vision."))
    assert full["backbone"] - frozen["backbone"] == vision > 0


def test_bfloat16_autocast_forward_runs_on_the_cpu(backbones):
    model = policy(backbones, lora={"r": 4})
    o = obs(4)
    with devices.autocast(torch.device("cpu"), "bfloat16"):
        actions, logp, value, x0 = model.act(o)
        again, entropy, v = model.evaluate(o, torch.as_tensor(actions), torch.as_tensor(x0))
        (-again.float().mean() + v.float().pow(2).mean()).backward()
    assert actions.shape == (4, 4, 7) and x0.shape == (4, 4, 7)
    assert all(np.isfinite(a).all() for a in (actions, logp, value)) and torch.isfinite(again).all()
    grads = [p.grad for n, p in model.named_parameters() if "lora_B" in n]
    assert grads and all(g is not None and torch.isfinite(g).all() for g in grads)


def test_on_the_meta_device_it_builds_shapes_without_reading_the_weights(backbones):
    with torch.device("meta"):  # how ebrl.sizes measures a run's weights message
        model = policy(backbones, lora={"r": 4})
    assert all(p.device.type == "meta" for p in model.parameters())
    real = policy(backbones, lora={"r": 4})
    assert {k: v.shape for k, v in model.state_dict().items()} == {k: v.shape for k, v in real.state_dict().items()}


def test_from_config_reads_the_policy_section():
    cfg = PolicySection(chunk=3, hidden=[16], denoise_steps=2)
    cfg.options = {"vision_config": {"model_type": "siglip_vision_model", "hidden_size": 16, "intermediate_size": 32,
                                     "num_hidden_layers": 1, "num_attention_heads": 2, "image_size": 16,
                                     "patch_size": 8},
                   "language_config": {"model_type": "llama", "vocab_size": 4096, "hidden_size": 16,
                                       "intermediate_size": 32, "num_hidden_layers": 1, "num_attention_heads": 2}}
    model = VLAPolicy.from_config(cfg, LAYOUT, 7, None)
    assert (model.kind, model.chunk, model.denoise_steps, model.encoder.out_dim) == ("vla", 3, 2, 16)
    assert model.predict_chunk(obs(2).numpy()).shape == (2, 3, 7)  # 48 px images resized to the tower's 16


LOW, HIGH = np.array([-1.0, -1, -1, -2, -2, -2, 0]), np.array([1.0, 1, 1, 2, 2, 2, 0.5])


def tokens_policy(backbones, **options):
    vision, language = backbones
    cfg = PolicySection(chunk=4, hidden=[32], denoise_steps=2)
    cfg.options = {"vision": str(vision), "language": str(language), "head": "tokens", "bins": 16, **options}
    return VLAPolicy.from_config(cfg, LAYOUT, 7, (LOW, HIGH)), cfg


def test_the_tokens_head_samples_bin_centres_whose_log_prob_training_recomputes(backbones):
    model, cfg = tokens_policy(backbones, lora={"r": 4})
    assert model.latent_shape == (0,) == VLAPolicy.latent_shape_of(cfg, 7)
    o = obs(8)
    actions, logp, values, latents = model.act(o)
    assert actions.shape == (8, 4, 7) and latents.shape == (8, 0)
    assert (actions >= LOW).all() and (actions <= HIGH).all()
    position = (actions - LOW) / ((HIGH - LOW) / 16) - 0.5  # each value is a bin's centre
    np.testing.assert_allclose(position, np.round(position), atol=1e-3)
    again, entropy, v = model.evaluate(o, torch.as_tensor(actions), torch.as_tensor(latents))
    torch.testing.assert_close(again, torch.as_tensor(logp), rtol=1e-5, atol=1e-4)
    assert torch.all(entropy <= 4 * 7 * np.log(16) + 1e-3) and torch.all(entropy > 0)
    chunk = model.predict_chunk(o.numpy())
    np.testing.assert_array_equal(chunk, model.predict_chunk(o.numpy()))  # the most likely bins
    learner = PPO(model, PPO_CFG, lr=1e-2)
    before = backbone_weights(model)
    batch = Batch(obs=o, actions=torch.as_tensor(actions), latents=torch.as_tensor(latents),
                  logprobs=torch.as_tensor(logp), advantages=torch.randn(8), returns=torch.randn(8),
                  values=torch.as_tensor(values), versions=np.zeros(8, np.int64))
    assert np.isfinite(learner.update(batch)["policy_loss"])
    assert all(torch.equal(before[n], p) for n, p in backbone_weights(model).items())
    assert not torch.allclose(model.evaluate(o, torch.as_tensor(actions), torch.as_tensor(latents))[0], again)


def test_the_tokens_head_needs_finite_bounds(backbones):
    with pytest.raises(ValueError, match="bins each action value within the env's action bounds; none"):
        VLAPolicy.from_config(tokens_policy(backbones)[1], LAYOUT, 7, None)
    with pytest.raises(ValueError, match="within finite action bounds"):
        VLAPolicy.from_config(tokens_policy(backbones)[1], LAYOUT, 7, (LOW, np.full(7, np.inf)))


@pytest.mark.parametrize("options, message", [
    ({"visoin": "x"}, r"unknown option\(s\) \['visoin'\]"),
    ({"vision_config": {"model_type": "siglip_vision_model"}}, "exactly one of vision .* and vision_config"),
    ({"vision": "/nonexistent/siglip"}, r"policy.options.vision = '/nonexistent/siglip': no config.json"),
    ({"vision": "", "vision_config": {"hidden_size": 8}}, "vision_config: expected a table with model_type"),
    ({"images": ["top"]}, "policy.options.images: 'top' is not a image field"),
    ({"instruction": "proprio"}, "policy.options.instruction: 'proprio' is not a tokens field"),
    ({"head": "diffusion"}, "policy.options.head = 'diffusion': expected one of flow, tokens"),
    ({"bins": 16}, "policy.options.bins is the tokens head's"),
    ({"freeze": ["arm"]}, "policy.options.freeze"),
    ({"lora": {"rank": 4}}, r"policy.options.lora: unknown key\(s\) \['rank'\]"),
])
def test_wrong_options_are_errors_that_name_the_option(backbones, options, message):
    with pytest.raises(ValueError, match=message):
        policy(backbones, **options)


def test_a_decoder_vocabulary_smaller_than_the_instruction_ids_is_refused(tmp_path, backbones):
    LlamaModel(LlamaConfig(vocab_size=1000, hidden_size=32, intermediate_size=64, num_hidden_layers=1,
                           num_attention_heads=2)).save_pretrained(tmp_path / "small")
    with pytest.raises(ValueError, match="decoder's vocabulary has 1000 ids; the instruction's token ids"):
        policy((backbones[0], tmp_path / "small"))
    assert policy((backbones[0], tmp_path / "small"), instruction="").encoder.instruction == ""  # no instruction


def test_a_directory_that_is_not_the_backbone_it_is_given_as_is_refused(tmp_path, backbones):
    with pytest.raises(ValueError, match="policy.options.vision: LlamaModel is not a vision tower"):
        policy((backbones[1], backbones[1]))
    shutil.copytree(backbones[0], tmp_path / "deeper")  # its config asks for a layer the weights do not have
    config = json.loads((tmp_path / "deeper" / "config.json").read_text())
    (tmp_path / "deeper" / "config.json").write_text(json.dumps({**config, "num_hidden_layers": 3}))
    with pytest.raises(ValueError, match=r"policy.options.vision = .*deeper': weights missing from the directory"):
        policy((tmp_path / "deeper", backbones[1]))


def test_lora_without_peft_is_a_clear_error(backbones, monkeypatch):
    monkeypatch.setitem(sys.modules, "peft", None)  # import peft raises ImportError
    with pytest.raises(ValueError, match=r"policy.options.lora needs peft: pip install 'ebrl\[vla\]'"):
        policy(backbones, lora={"r": 4})


@pytest.mark.gpu
@pytest.mark.skipif(not torch.cuda.is_available(), reason="needs a CUDA device (benchmarks/gpu/check.sh runs it)")
@pytest.mark.parametrize("dtype", ["float32", "bfloat16"])
def test_on_a_gpu_the_chunk_forward_captures_as_a_cuda_graph_and_follows_new_weights(backbones, dtype):
    from ebrl.policies import load_arrays, state_arrays
    from ebrl.policies.graphs import Actor

    model = policy(backbones, lora={"r": 4}).cuda().eval()
    actor, stage = Actor(model, "cudagraphs", dtype), devices.Staging(torch.device("cuda"))
    for _ in range(2):
        o = obs(4).numpy()
        actions, logp, value, x0 = actor(stage(o))
        assert actor.graphed and 4 in actor.graphs  # captured, not fallen back to eager
        with devices.autocast(torch.device("cuda"), dtype):
            again, _, v = model.evaluate(*(torch.from_numpy(x).cuda() for x in (o, actions, x0)))
        tol = 1e-3 if dtype == "float32" else 0.5  # bfloat16: a few ulps of values of 10-30
        torch.testing.assert_close(torch.from_numpy(logp), again.float().cpu(), rtol=1e-3, atol=tol)
        fresh = state_arrays(model)
        load_arrays(model, {k: a + 0.05 if "lora_B" in k else a for k, a in fresh.items()})
        assert not np.allclose(actor(stage(o))[2], value)  # the replay reads the new weights


def vla_overrides(vision, language, *more):
    return ('policy.kind="vla"', f'policy.options.vision="{vision}"', f'policy.options.language="{language}"',
            "policy.options.lora.r=4", "policy.hidden=[32, 32]", "policy.denoise_steps=2", "run.iterations=2",
            "sim.groups=1", "sim.envs_per_group=2", *more)


def trains_and_loads(tmp_path, config, overrides, run, layout_images, timeout):
    """A real `ebrl up` of ``config`` with a tiny VLA (LoRA) for 2 PPO updates; then the weights' directories are
    deleted and the run's policy loads from its checkpoint alone and predicts chunks."""
    import ebrl

    vision, language = save_backbones(tmp_path / "weights")
    code, out, stats = helpers.run_collecting_stats(tmp_path / "runs", config, *vla_overrides(vision, language),
                                                    *overrides, run=run, timeout=timeout)
    assert code == 0, out
    assert stats["train/0"][-1]["train/policy_version"] == 2
    shutil.rmtree(tmp_path / "weights")
    run_dir = next((tmp_path / "runs").glob(f"{run}-*"))
    loaded = ebrl.load_policy(run_dir)
    assert loaded.kind == "vla" and [f.name for f in loaded.layout.of_kind("image")] == layout_images
    assert loaded.model.trainable()["backbone"] == 0 and loaded.model.trainable()["lora"] > 0
    batch = sample_observations(loaded.layout, 2)
    chunk = loaded.predict_chunk(batch)
    assert chunk.shape == (2, 8, loaded.action_dim) and np.isfinite(chunk).all()
    action, _ = loaded.predict(batch[0])
    assert action.shape == (loaded.action_dim,)


def test_trains_through_ebrl_up_on_robosuite_cameras_and_loads_with_load_policy(tmp_path):
    trains_and_loads(tmp_path, "configs/robosuite_lift_rgb.toml",
                     ("env.kwargs.image_size=32", "train.batch_size=16", "env.max_episode_steps=24"),
                     "vla-lift", ["image"], timeout=300)


@pytest.mark.slow
@needs_libero
def test_trains_through_ebrl_up_on_libero_cameras_and_loads_with_load_policy(tmp_path):
    trains_and_loads(tmp_path, "configs/libero_spatial.toml",
                     ("env.kwargs.image_size=64", "env.kwargs.tasks=[0]", "train.batch_size=16",
                      "sim.segment_length=8"), "vla-libero", ["agentview", "wrist"], timeout=900)
