"""A transformer observation backbone (``policy.backbone = "transformer"``): image patches, proprioception and
instruction tokens in, one feature vector out — the shape of the VLA policies embodied RL fine-tunes.

Tokens: every image field is cut into ``patch`` x ``patch`` patches, each linearly embedded (a strided
convolution) with a learned position; the vector fields together are one token; every instruction token id
is embedded with its position (padding, id 0, is masked out); a learned [CLS] token goes first. A
pre-norm ``nn.TransformerEncoder`` of ``depth`` layers, ``width`` wide with ``heads`` heads and a 4x MLP,
runs over them; the features are the final [CLS] state (layer-normed). Parameters: about 12 * width^2 per
layer (width 1024, depth 24: 302M), plus the embeddings.
"""

from __future__ import annotations

import torch
from torch import nn

from ebrl.envs.obs import VOCAB_SIZE, ObsLayout


class TransformerEncoder(nn.Module):
    def __init__(self, layout: ObsLayout, width: int, depth: int, heads: int, patch: int):
        super().__init__()
        if width % heads:
            raise ValueError(f"policy.width = {width} is not a multiple of policy.heads = {heads}")
        self.layout, self.out_dim = layout, width
        self.image_fields = [f.name for f in layout.of_kind("image")]
        self.vector_fields = [f.name for f in layout.of_kind("vector")]
        self.token_fields = [f.name for f in layout.of_kind("tokens")]
        self.patches = nn.ModuleList()
        self.image_pos = nn.ParameterList()
        for field in layout.of_kind("image"):
            channels, height, width_px = field.shape
            if height % patch or width_px % patch:
                raise ValueError(f"policy.patch = {patch} does not divide the {field.name} image ({height}x{width_px})")
            self.patches.append(nn.Conv2d(channels, width, kernel_size=patch, stride=patch))
            self.image_pos.append(nn.Parameter(0.02 * torch.randn(height // patch * (width_px // patch), width)))
        vector_size = sum(f.size for f in layout.of_kind("vector"))
        self.vectors = nn.Linear(vector_size, width) if vector_size else None
        token_count = sum(f.size for f in layout.of_kind("tokens"))
        self.tokens = nn.Embedding(VOCAB_SIZE, width, padding_idx=0) if token_count else None
        self.token_pos = nn.Parameter(0.02 * torch.randn(token_count, width)) if token_count else None
        self.cls = nn.Parameter(0.02 * torch.randn(1, 1, width))
        block = nn.TransformerEncoderLayer(width, heads, 4 * width, dropout=0.0, activation="gelu", batch_first=True,
                                           norm_first=True)
        self.blocks = nn.TransformerEncoder(block, depth, enable_nested_tensor=False)
        self.norm = nn.LayerNorm(width)

    def forward(self, obs: torch.Tensor) -> torch.Tensor:
        parts, batch = self.layout.split(obs), obs.shape[0]
        seq = [self.cls.expand(batch, -1, -1)]
        for name, embed, pos in zip(self.image_fields, self.patches, self.image_pos):
            seq.append(embed(parts[name]).flatten(2).transpose(1, 2) + pos)
        if self.vectors is not None:
            seq.append(self.vectors(torch.cat([parts[n].reshape(batch, -1) for n in self.vector_fields], 1))[:, None])
        pad = torch.zeros(batch, sum(s.shape[1] for s in seq), dtype=torch.bool, device=obs.device)
        if self.tokens is not None:
            ids = torch.cat([parts[n].reshape(batch, -1) for n in self.token_fields], 1).long()
            seq.append(self.tokens(ids) + self.token_pos)
            pad = torch.cat([pad, ids == 0], 1)
        x = self.blocks(torch.cat(seq, 1), src_key_padding_mask=pad)
        return self.norm(x[:, 0])
