"""A vision-language-action policy (``policy.kind = "vla"``): a Hugging Face transformers vision tower and language
decoder under an action head (EBRL's flow-matching chunk head, or discrete action tokens), optionally
LoRA-adapted (peft) for RL fine-tuning.

The observation becomes one sequence of embeddings for the decoder, as PaliGemma and OpenVLA-OFT build theirs:

    [camera 1's patches] [camera 2's patches] ... [proprioception] [instruction tokens] [readout]

Each camera image (``[0, 1]``, channel-first) is resized to the vision tower's ``image_size``, standardised by the
tower's ``image_mean``/``image_std`` and run through the tower (all cameras as one batch); its patch states go
through a linear projector to the decoder's width, plus a learned embedding per camera. The vector fields
(proprioception) are one linear token. The instruction's ids index the decoder's own embedding table (padding,
id 0, is masked out). A learned readout token goes last; the decoder is causal, so its final state has seen
everything: it is the feature vector the flow head (:class:`~ebrl.policies.flow.FlowPolicy`: its velocity MLP
and critic) reads. The backbone runs once per chunk; the N denoising steps run only the small velocity MLP.
The tokens head appends K x A query tokens after the readout instead and reads each one's state.

``policy.options`` (docs/vla.md):

- ``vision`` / ``language``: a local directory (``save_pretrained``'s: ``config.json`` and weights) loaded with
  ``from_pretrained``, never from the network; or ``vision_config`` / ``language_config``: a transformers config
  as a table (``model_type`` and its fields), randomly initialised. Any vision model that maps ``pixel_values``
  to ``last_hidden_state`` (SigLIP, CLIP's, DINOv2, ViT; of a two-tower SigLIP or CLIP checkpoint, its vision
  tower) and any decoder that takes ``inputs_embeds`` (Llama, Qwen2, Gemma, Mistral; a ``*ForCausalLM``
  checkpoint without its LM head). SigLIP's pooling head is not used and not built.
- ``images`` (default: every image field), ``instruction`` (default: the layout's tokens field; "" for none),
  ``proprio`` (default: every vector field): the observation fields it reads.
- ``image_mean`` / ``image_std``: per channel; default the vision directory's ``preprocessor_config.json``,
  else 0.5 (SigLIP's).
- ``head``: ``"flow"`` (the flow-matching chunk head on the readout's state) or ``"tokens"`` (discrete action
  tokens: each action value one of ``bins`` (256) bins of the env's action bounds, the chunk's K x A tokens
  decoded in parallel from learned query tokens: :class:`VLATokensPolicy`).
- ``freeze``: backbones (``"vision"``, ``"language"``) whose weights stay as loaded; their LoRA adapters too
  are left out.
- ``lora``: a table (``r`` 8, ``alpha`` 16, ``dropout`` 0.0, ``target_modules``, ``modules_to_save``): LoRA
  adapters (peft) on the backbones not frozen; their base weights never train. Absent: full fine-tuning.
- ``attn_implementation``: transformers' attention kernel, ``"sdpa"`` (default) or ``"eager"``.

:attr:`VLAPolicy.options` is the resolved form, with both backbones' configs inline (``vision_config``,
``language_config``) and no path: what a checkpoint stores to rebuild the architecture without any external file
(its weights come from the checkpoint's state dict). transformers and peft are imported by this module only.
"""

from __future__ import annotations

import inspect
import json
import logging
import os
import warnings
from typing import Any

import numpy as np
import torch
import torch.nn.functional as F
from torch import nn

from ebrl.envs.obs import VOCAB_SIZE, ObsField, ObsLayout
from ebrl.policies.base import ChunkPolicy, Tensors3
from ebrl.policies.flow import FlowPolicy
from ebrl.policies.nets import layer, mlp

log = logging.getLogger("ebrl.policies")

BACKBONES = ("vision", "language")
HEADS = ("flow", "tokens")
BINS = 256  # head = "tokens": bins per action value (RT-2's and OpenVLA's 256)
ATTENTION = ("sdpa", "eager")
LORA_DEFAULTS: dict[str, Any] = {"r": 8, "alpha": 16, "dropout": 0.0,
                                 # attention projections of Llama-style decoders (o_proj) and of SigLIP/CLIP
                                 # towers (out_proj)
                                 "target_modules": ["q_proj", "k_proj", "v_proj", "o_proj", "out_proj"],
                                 "modules_to_save": []}
OPTIONS = ("vision", "vision_config", "language", "language_config", "images", "instruction", "proprio",
           "image_mean", "image_std", "head", "bins", "freeze", "lora", "attn_implementation")
SIGLIP_MEAN = [0.5, 0.5, 0.5]  # SigLIP's processor: pixels / 255 * 2 - 1


def _transformers() -> Any:
    try:
        import transformers
    except ImportError:
        raise ValueError("policy.kind = 'vla' needs Hugging Face transformers: pip install 'ebrl[vla]'") from None
    transformers.utils.logging.disable_progress_bar()  # "Loading weights" bars in every service's log
    return transformers


def resolve_options(options: dict[str, Any], layout: ObsLayout) -> tuple[dict[str, Any], dict[str, str]]:
    """``policy.options`` checked against ``layout`` and completed: (the resolved options, JSON-able, with both
    backbones' configs inline; the local directories to load weights from, by backbone). ValueError naming the
    option for anything wrong."""
    unknown = sorted(set(options) - set(OPTIONS))
    if unknown:
        raise ValueError(f"policy.options: unknown option(s) {unknown} for policy.kind = 'vla' (known: "
                         f"{', '.join(OPTIONS)})")
    out: dict[str, Any] = {}
    sources: dict[str, str] = {}
    configs = {}
    for name in BACKBONES:
        configs[name], path = _config(name, options)
        if path:
            sources[name] = path
        out[f"{name}_config"] = configs[name].to_diff_dict()
    out.update(_fields(options, layout))
    mean, std = _normalisation(options, sources.get("vision", ""))
    out["image_mean"], out["image_std"] = mean, std
    vocab = int(getattr(configs["language"], "vocab_size", 0) or 0)
    if out["instruction"] and vocab < VOCAB_SIZE:
        raise ValueError(f"policy.options.language: the decoder's vocabulary has {vocab} ids; the instruction's "
                         f"token ids (ebrl.envs.obs.tokenize) go up to {VOCAB_SIZE - 1}")
    out["head"] = str(options.get("head", "flow"))
    if out["head"] not in HEADS:
        raise ValueError(f"policy.options.head = {out['head']!r}: expected one of {', '.join(HEADS)}")
    if out["head"] == "tokens":
        out["bins"] = int(options.get("bins", BINS))
        if out["bins"] < 2:
            raise ValueError(f"policy.options.bins = {out['bins']}: at least 2")
    elif "bins" in options:
        raise ValueError("policy.options.bins is the tokens head's; policy.options.head is 'flow'")
    out["freeze"] = list(options.get("freeze", []))
    if set(out["freeze"]) - set(BACKBONES):
        raise ValueError(f"policy.options.freeze = {out['freeze']}: expected names among {', '.join(BACKBONES)}")
    out["lora"] = _lora(options.get("lora") or {})
    out["attn_implementation"] = str(options.get("attn_implementation", "sdpa"))
    if out["attn_implementation"] not in ATTENTION:
        raise ValueError(f"policy.options.attn_implementation = {out['attn_implementation']!r}: expected one of "
                         f"{', '.join(ATTENTION)}")
    return out, sources


def _config(name: str, options: dict[str, Any]) -> tuple[Any, str]:
    """The transformers config of backbone ``name`` and the directory of its weights ("" for random init)."""
    transformers = _transformers()
    path, inline = options.get(name, ""), options.get(f"{name}_config")
    if bool(path) == bool(inline):
        raise ValueError(f"policy.options: give exactly one of {name} (a local directory of weights) and "
                         f"{name}_config (a transformers config, randomly initialised)")
    if path:
        path = os.path.abspath(os.path.expanduser(str(path)))
        if not os.path.isfile(os.path.join(path, "config.json")):
            raise ValueError(f"policy.options.{name} = {options[name]!r}: no config.json in {path} (a directory "
                             "written by save_pretrained; nothing is downloaded)")
        config = transformers.AutoConfig.from_pretrained(path, local_files_only=True)
        if name == "vision" and getattr(config, "vision_config", None) is not None:
            config = config.vision_config  # a two-tower checkpoint (SiglipModel, CLIPModel): its vision tower
    else:
        if not isinstance(inline, dict) or "model_type" not in inline:
            raise ValueError(f"policy.options.{name}_config: expected a table with model_type (a transformers "
                             f"config), got {inline!r}")
        fields = dict(inline)
        try:
            config = transformers.AutoConfig.for_model(fields.pop("model_type"), **fields)
        except (ValueError, KeyError) as exc:
            raise ValueError(f"policy.options.{name}_config: {exc}") from None
    if getattr(config, "vision_use_head", False):
        config.vision_use_head = False  # SigLIP's attention-pooling head: the patch states are read, not it
    return config, path


def _fields(options: dict[str, Any], layout: ObsLayout) -> dict[str, Any]:
    """The observation fields the policy reads, checked against ``layout``."""
    kinds = {f.name: f.kind for f in layout.fields}
    tokens = [f.name for f in layout.of_kind("tokens")]
    out = {"images": list(options.get("images", [f.name for f in layout.of_kind("image")])),
           "instruction": str(options.get("instruction", tokens[0] if tokens else "")),
           "proprio": list(options.get("proprio", [f.name for f in layout.of_kind("vector")]))}
    wanted = [(n, "image", "images") for n in out["images"]] + [(n, "vector", "proprio") for n in out["proprio"]]
    if out["instruction"]:
        wanted.append((out["instruction"], "tokens", "instruction"))
    for name, kind, option in wanted:
        if kinds.get(name) != kind:
            raise ValueError(f"policy.options.{option}: {name!r} is not a {kind} field of the observation "
                             f"({layout.describe()})")
    if not out["images"]:
        raise ValueError(f"policy.options.images: the observation has no image field to read ({layout.describe()})")
    shapes = {field(layout, n).shape for n in out["images"]}
    if len(shapes) > 1:
        raise ValueError(f"policy.options.images: the cameras' images differ in shape ({sorted(shapes)})")
    return out


def field(layout: ObsLayout, name: str) -> ObsField:
    return next(f for f in layout.fields if f.name == name)


def _normalisation(options: dict[str, Any], vision_dir: str) -> tuple[list[float], list[float]]:
    """image_mean and image_std: the options', else the vision directory's preprocessor_config.json, else 0.5."""
    processor: dict[str, Any] = {}
    file = os.path.join(vision_dir, "preprocessor_config.json") if vision_dir else ""
    if file and os.path.isfile(file):
        with open(file) as fh:
            processor = json.load(fh)
    mean = [float(x) for x in options.get("image_mean", processor.get("image_mean", SIGLIP_MEAN))]
    std = [float(x) for x in options.get("image_std", processor.get("image_std", SIGLIP_MEAN))]
    if len(mean) != 3 or len(std) != 3 or min(std) <= 0:
        raise ValueError(f"policy.options.image_mean/image_std: three values per channel, std > 0 (got {mean}, "
                         f"{std})")
    return mean, std


def _lora(table: dict[str, Any]) -> dict[str, Any]:
    if not table:
        return {}
    unknown = sorted(set(table) - set(LORA_DEFAULTS))
    if unknown:
        raise ValueError(f"policy.options.lora: unknown key(s) {unknown} (known: {', '.join(LORA_DEFAULTS)})")
    try:
        import peft  # noqa: F401
    except ImportError:
        raise ValueError("policy.options.lora needs peft: pip install 'ebrl[vla]' (or drop the lora table to "
                         "fine-tune every weight)") from None
    out = {**LORA_DEFAULTS, **table}
    if int(out["r"]) < 1 or not 0.0 <= float(out["dropout"]) < 1.0:
        raise ValueError(f"policy.options.lora: r >= 1 and 0 <= dropout < 1 (got r = {out['r']}, dropout = "
                         f"{out['dropout']})")
    return {"r": int(out["r"]), "alpha": float(out["alpha"]), "dropout": float(out["dropout"]),
            "target_modules": list(out["target_modules"]), "modules_to_save": list(out["modules_to_save"])}


def load_backbone(name: str, config: Any, path: str, attn: str) -> nn.Module:
    """Backbone ``name``: its weights from the local directory ``path`` (float32; every weight of the
    architecture must be there), or randomly initialised from ``config`` (no path, or under torch's meta device:
    shapes only)."""
    transformers = _transformers()
    if not path or torch.get_default_device().type == "meta":
        return _interface(name, transformers.AutoModel.from_config(config, attn_implementation=attn,
                                                                   dtype=torch.float32))
    verbosity = transformers.utils.logging.get_verbosity()
    transformers.utils.logging.set_verbosity_error()  # its table of unused weights (SigLIP's head, an LM head)
    try:
        model, info = transformers.AutoModel.from_pretrained(path, config=config, local_files_only=True,
                                                             attn_implementation=attn, dtype=torch.float32,
                                                             output_loading_info=True)
    finally:
        transformers.utils.logging.set_verbosity(verbosity)
    missing = sorted(info.get("missing_keys") or [])
    if missing:
        raise ValueError(f"policy.options.{name} = {path!r}: weights missing from the directory ({len(missing)}, "
                         f"e.g. {', '.join(missing[:3])}): not a {type(model).__name__} checkpoint")
    return _interface(name, model)


def _interface(name: str, model: nn.Module) -> nn.Module:
    """``model`` if it is a vision tower (``forward(pixel_values=...)``) or a decoder (``inputs_embeds``, an input
    embedding table), as backbone ``name`` must be; else ValueError naming the option."""
    arguments = inspect.signature(model.forward).parameters
    wanted = "pixel_values" if name == "vision" else "inputs_embeds"
    if wanted not in arguments or (name == "language" and model.get_input_embeddings() is None):
        what = "a vision tower" if name == "vision" else "a decoder with an input embedding table"
        raise ValueError(f"policy.options.{name}: {type(model).__name__} is not {what} (its forward takes no "
                         f"{wanted})")
    return model


class VLABackbone(nn.Module):
    """Flat observations -> the decoder's final state at the readout token, ``[B, out_dim]`` (its width); with
    ``queries`` learned query tokens after the readout (the tokens head), the states of the readout and of each
    query, ``[B, 1 + queries, out_dim]``."""

    def __init__(self, layout: ObsLayout, options: dict[str, Any], sources: dict[str, str], queries: int = 0):
        super().__init__()
        transformers = _transformers()
        self.layout, attn = layout, options["attn_implementation"]
        self.image_fields, self.proprio_fields = options["images"], options["proprio"]
        self.instruction = options["instruction"]
        vision_cfg = transformers.AutoConfig.for_model(**options["vision_config"])
        language_cfg = transformers.AutoConfig.for_model(**options["language_config"])
        self.vision = load_backbone("vision", vision_cfg, sources.get("vision", ""), attn)
        self.language = load_backbone("language", language_cfg, sources.get("language", ""), attn)
        size = vision_cfg.image_size
        self.image_size = (size, size) if isinstance(size, int) else tuple(size)
        width = self.out_dim = int(language_cfg.hidden_size)
        self.projector = nn.Linear(int(vision_cfg.hidden_size), width)
        self.cameras = nn.Parameter(0.02 * torch.randn(len(self.image_fields), 1, width))
        proprio = sum(field(layout, n).size for n in self.proprio_fields)
        self.proprio = nn.Linear(proprio, width) if proprio else None
        self.readout = nn.Parameter(0.02 * torch.randn(1, 1 + queries, width))  # the readout, then the queries
        self.register_buffer("mean", torch.tensor(options["image_mean"]).view(1, 3, 1, 1), persistent=False)
        self.register_buffer("std", torch.tensor(options["image_std"]).view(1, 3, 1, 1), persistent=False)
        self.adapt(options["lora"], options["freeze"])

    def adapt(self, lora: dict[str, Any], freeze: list[str]) -> None:
        """What of the backbones trains: LoRA adapters on those not in ``freeze`` (their base weights fixed), or
        without ``lora`` every weight of those not in ``freeze``."""
        for name in BACKBONES:
            module = getattr(self, name)
            if name in freeze or lora:
                module.requires_grad_(False)
            if lora and name not in freeze:
                from peft import LoraConfig, get_peft_model

                config = LoraConfig(r=lora["r"], lora_alpha=lora["alpha"], lora_dropout=lora["dropout"],
                                    target_modules=lora["target_modules"],
                                    modules_to_save=lora["modules_to_save"] or None)
                with warnings.catch_warnings():  # peft asks a deprecated transformers property
                    warnings.simplefilter("ignore", FutureWarning)
                    setattr(self, name, get_peft_model(module, config))

    def forward(self, obs: torch.Tensor) -> torch.Tensor:
        parts, batch = self.layout.split(obs), obs.shape[0]
        images = torch.stack([parts[n] for n in self.image_fields], 1).flatten(0, 1)  # [B * cameras, C, H, W]
        if tuple(images.shape[-2:]) != self.image_size:
            images = F.interpolate(images, size=self.image_size, mode="bilinear", align_corners=False)
        patches = self.vision(pixel_values=(images - self.mean) / self.std).last_hidden_state
        patches = self.projector(patches).unflatten(0, (batch, len(self.image_fields))) + self.cameras
        seq = [patches.flatten(1, 2)]
        if self.proprio is not None:
            seq.append(self.proprio(torch.cat([parts[n].reshape(batch, -1) for n in self.proprio_fields], 1))[:, None])
        seen = [torch.ones(batch, sum(s.shape[1] for s in seq), dtype=torch.long, device=obs.device)]
        if self.instruction:
            ids = parts[self.instruction].reshape(batch, -1).long()
            seq.append(self.language.get_input_embeddings()(ids).to(seq[0].dtype))
            seen.append((ids != 0).long())
        readout = self.readout.shape[1]
        seq.append(self.readout.expand(batch, -1, -1).to(seq[0].dtype))
        seen.append(torch.ones(batch, readout, dtype=torch.long, device=obs.device))
        hidden = self.language(inputs_embeds=torch.cat(seq, 1), attention_mask=torch.cat(seen, 1),
                               use_cache=False).last_hidden_state
        return hidden[:, -1].float() if readout == 1 else hidden[:, -readout:].float()


class VLAParts:
    """What both heads share: which parameters train, and a log line saying so."""

    def trainable(self) -> dict[str, int]:
        """Parameters that train, by part: ``lora`` (the adapters), ``backbone`` (the transformers models' own
        weights), ``head`` (projector, camera/proprioception/readout embeddings, the action head, critic)."""
        out = {"lora": 0, "backbone": 0, "head": 0}
        for name, p in self.named_parameters():  # type: ignore[attr-defined]
            if p.requires_grad:
                part = ("lora" if "lora_" in name else "backbone"
                        if name.startswith(("encoder.vision.", "encoder.language.")) else "head")
                out[part] += p.numel()
        return out

    def describe(self) -> None:
        options, backbone = self.options, self.encoder  # type: ignore[attr-defined]
        frozen = ",".join(options["freeze"])
        how = "LoRA" if options["lora"] else f"{frozen} frozen" if frozen else "full fine-tuning"
        log.info("vla: vision %s, language %s (%s), %s head, %.1fM parameters, %.2fM of them train",
                 type(backbone.vision).__name__, type(backbone.language).__name__, how, options["head"],
                 sum(p.numel() for p in self.parameters()) / 1e6,  # type: ignore[attr-defined]
                 sum(self.trainable().values()) / 1e6)


class VLAPolicy(VLAParts, FlowPolicy):
    """pi(a_{t:t+K} | o_t, x_0) of the flow head on a transformers vision-language backbone (module docstring);
    ``policy.options.head = "tokens"`` builds a :class:`VLATokensPolicy` instead."""

    kind = "vla"
    backbones = ("conv",)  # policy.backbone is not read: the backbone is policy.options' vision and language

    def __init__(self, layout: ObsLayout, action_dim: int, chunk: int, hidden: list[int], denoise_steps: int,
                 init_log_std: float = -0.5, options: dict[str, Any] | None = None):
        resolved, sources = resolve_options(dict(options or {}), layout)
        if resolved["head"] != "flow":
            raise ValueError(f"policy.options.head = {resolved['head']!r}: VLAPolicy is the flow head's "
                             "(VLAPolicy.from_config builds either)")
        backbone = VLABackbone(layout, resolved, sources)
        super().__init__(layout, action_dim, chunk, hidden, [], 0, denoise_steps, init_log_std, encoder=backbone)
        self.options = resolved  # what a checkpoint stores: rebuilds the architecture with no external file
        self.describe()

    @classmethod
    def from_config(cls, cfg: Any, layout: ObsLayout, action_dim: int, bounds: Any = None) -> ChunkPolicy:
        """The policy a PolicySection ``cfg`` describes (``cfg.options``: the module docstring's options): this
        class for the flow head, :class:`VLATokensPolicy` (which needs the env's action ``bounds``) for tokens."""
        options = dict(cfg.options)
        if options.get("head") == "tokens":
            if bounds is None:
                raise ValueError("policy.options.head = 'tokens' bins each action value within the env's action "
                                 "bounds; none were given")
            return VLATokensPolicy(layout, action_dim, cfg.chunk, list(cfg.hidden), bounds, options)
        return cls(layout, action_dim, cfg.chunk, list(cfg.hidden), cfg.denoise_steps, cfg.init_log_std, options)

    @classmethod
    def latent_shape_of(cls, cfg: Any, action_dim: int) -> tuple[int, ...]:
        """The flow head's x_0, [K, A]; the tokens head has none."""
        head = cfg.options.get("head", "flow")
        return (0,) if head == "tokens" else (cfg.chunk, action_dim)


class VLATokensPolicy(VLAParts, ChunkPolicy):
    """pi(a_{t:t+K} | o_t) as K x A discrete action tokens (``policy.options.head = "tokens"``).

    Each action value is one of ``bins`` uniform bins of its bound range, as RT-2 and OpenVLA discretise actions;
    the action sent is the bin's centre. The K x A tokens are decoded in parallel, as OpenVLA-OFT does: K x A
    learned query tokens follow the readout in the decoder's sequence, and each one's final state gives the
    logits of its action value's bins (one linear map shared by all). Given the observation the K x A values are
    independent categoricals, so log pi(a | o) is the exact sum of their log-probs and the entropy the sum of
    theirs; there are no latents. The critic reads the readout's state, which the causal decoder computes before
    (and without) the queries.
    """

    kind = "vla"
    backbones = ("conv",)
    latent_shape = (0,)

    def __init__(self, layout: ObsLayout, action_dim: int, chunk: int, hidden: list[int],
                 bounds: tuple[Any, Any], options: dict[str, Any] | None = None):
        super().__init__()
        resolved, sources = resolve_options({**(options or {}), "head": "tokens"}, layout)
        low, high = (np.asarray(b, np.float64).reshape(-1) for b in bounds)
        finite = np.isfinite(low).all() and np.isfinite(high).all() and (high > low).all()
        if low.shape != (action_dim,) or not finite:
            raise ValueError(f"policy.options.head = 'tokens' bins each action value within finite action bounds; "
                             f"the env's are {low.tolist()} .. {high.tolist()}")
        self.layout, self.action_dim, self.chunk, self.bins = layout, action_dim, chunk, resolved["bins"]
        n = chunk * action_dim
        self.encoder = VLABackbone(layout, resolved, sources, queries=n)
        self.logits = layer(self.encoder.out_dim, self.bins, 0.01)
        self.critic = mlp(self.encoder.out_dim, hidden, 1, 1.0)
        # the bins of each of the chunk's K x A values: rebuilt from the bounds, not weights
        self.register_buffer("low", torch.tensor(np.tile(low, chunk), dtype=torch.float32), persistent=False)
        self.register_buffer("step", torch.tensor(np.tile((high - low) / self.bins, chunk), dtype=torch.float32),
                             persistent=False)
        self.options = resolved
        self.describe()

    def heads(self, obs: torch.Tensor) -> tuple[torch.Tensor, torch.Tensor]:
        """Log-probs of every bin [B, K*A, bins] (float32) and the value [B], from one pass over flat ``obs``."""
        states = self.encoder(self.flat(obs))
        return F.log_softmax(self.logits(states[:, 1:]).float(), -1), self.critic(states[:, 0]).squeeze(-1).float()

    def actions_of(self, bins: torch.Tensor) -> torch.Tensor:
        """Bin indices [B, K*A] -> the bins' centres [B, K, A]."""
        return (self.low + (bins + 0.5) * self.step).reshape(bins.shape[0], self.chunk, self.action_dim)

    def sample(self, obs: np.ndarray | torch.Tensor) -> tuple[torch.Tensor, ...]:
        """Gumbel-max sampling of each token (no read-back to the host: capturable as a CUDA graph)."""
        logp, value = self.heads(obs)
        gumbel = -torch.log(-torch.log(torch.rand_like(logp).clamp_(1e-20, 1.0)))
        bins = (logp + gumbel).argmax(-1)
        taken = logp.gather(-1, bins[..., None]).squeeze(-1).sum(-1)
        return self.actions_of(bins), taken, value, logp.new_zeros(bins.shape[0], 0)

    def evaluate(self, obs: torch.Tensor, actions: torch.Tensor, latents: torch.Tensor) -> Tensors3:
        logp, value = self.heads(obs)
        flat = actions.reshape(actions.shape[0], -1).float()
        bins = ((flat - self.low) / self.step).floor().long().clamp_(0, self.bins - 1)  # a centre's own bin
        taken = logp.gather(-1, bins[..., None]).squeeze(-1).sum(-1)
        return taken, -(logp.exp() * logp).sum(-1).sum(-1), value

    def value(self, obs: torch.Tensor) -> torch.Tensor:
        return self.critic(self.encoder(self.flat(obs))[:, 0]).squeeze(-1)

    @torch.no_grad()
    def predict_chunk(self, obs: np.ndarray, deterministic: bool = True,
                      generator: torch.Generator | None = None) -> np.ndarray:
        """Deterministic: each token's most likely bin; else a sample, its noise drawn from ``generator``."""
        logp, _ = self.heads(obs)
        if not deterministic:
            uniform = torch.rand(tuple(logp.shape), generator=generator).to(logp.device).clamp_(1e-20, 1.0)
            logp = logp - torch.log(-torch.log(uniform))
        return self.actions_of(logp.argmax(-1)).cpu().numpy()
