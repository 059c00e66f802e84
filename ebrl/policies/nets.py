"""Building blocks shared by the policies: orthogonally initialised MLPs and the observation encoder."""

from __future__ import annotations

import math

import numpy as np
import torch
from torch import nn

from ebrl.envs.obs import VOCAB_SIZE, ObsField, ObsLayout


def layer(n_in: int, n_out: int, gain: float) -> nn.Linear:
    out = nn.Linear(n_in, n_out)
    nn.init.orthogonal_(out.weight, gain)
    nn.init.zeros_(out.bias)
    return out


def mlp(n_in: int, hidden: list[int], n_out: int | None, out_gain: float = 1.0,
        activation: type[nn.Module] = nn.Tanh) -> nn.Sequential:
    """Tanh MLP (or ``activation``); ``n_out=None`` ends after the last hidden layer (a trunk for several heads)."""
    layers: list[nn.Module] = []
    for width in hidden:
        layers += [layer(n_in, width, math.sqrt(2)), activation()]
        n_in = width
    if n_out is not None:
        layers.append(layer(n_in, n_out, out_gain))
    return nn.Sequential(*layers)


def width(n_in: int, hidden: list[int]) -> int:
    """Output width of ``mlp(n_in, hidden, None)``."""
    return hidden[-1] if hidden else n_in


class ConvEncoder(nn.Module):
    """One channel-first image -> features: 3x3 convs of stride 2 with ReLU, flatten, linear, ReLU."""

    def __init__(self, shape: tuple[int, ...], channels: list[int], out_dim: int):
        super().__init__()
        convs: list[nn.Module] = []
        n_in = shape[0]
        for n_out in channels:
            conv = nn.Conv2d(n_in, n_out, kernel_size=3, stride=2, padding=1)
            nn.init.orthogonal_(conv.weight, math.sqrt(2))
            nn.init.zeros_(conv.bias)
            convs += [conv, nn.ReLU()]
            n_in = n_out
        self.convs = nn.Sequential(*convs, nn.Flatten())
        with torch.no_grad():  # the flattened size for this image size, whatever it is
            flat = self.convs(torch.zeros(1, *shape)).shape[1]
        self.project = nn.Sequential(layer(flat, out_dim, math.sqrt(2)), nn.ReLU())

    def forward(self, image: torch.Tensor) -> torch.Tensor:
        return self.project(self.convs(image))


class ObsEncoder(nn.Module):
    """Flat observations -> one feature vector per env, each kind of field by its own encoder.

    Every image field gets a :class:`ConvEncoder`; the vector fields (state, proprioception),
    concatenated, a linear layer with tanh; the token fields, concatenated, a mean
    ``EmbeddingBag`` that skips padding (id 0). Each part is ``embed_dim`` wide; the
    features are their concatenation, ``out_dim`` wide.
    """

    def __init__(self, layout: ObsLayout, channels: list[int], embed_dim: int):
        super().__init__()
        self.layout = layout
        self.image_fields = [f.name for f in layout.of_kind("image")]
        self.vector_fields = [f.name for f in layout.of_kind("vector")]
        self.token_fields = [f.name for f in layout.of_kind("tokens")]
        self.images = nn.ModuleList(ConvEncoder(f.shape, channels, embed_dim) for f in layout.of_kind("image"))
        self.vectors = (nn.Sequential(layer(_size(layout.of_kind("vector")), embed_dim, math.sqrt(2)), nn.Tanh())
                        if self.vector_fields else None)
        self.tokens = (nn.EmbeddingBag(VOCAB_SIZE, embed_dim, mode="mean", padding_idx=0)
                       if self.token_fields else None)
        self.out_dim = embed_dim * (len(self.images) + bool(self.vector_fields) + bool(self.token_fields))

    def forward(self, obs: torch.Tensor) -> torch.Tensor:
        parts = self.layout.split(obs)
        batch = obs.shape[0]
        features = [encode(parts[name]) for name, encode in zip(self.image_fields, self.images)]
        if self.vectors is not None:
            features.append(self.vectors(torch.cat([parts[n].reshape(batch, -1) for n in self.vector_fields], 1)))
        if self.tokens is not None:
            ids = torch.cat([parts[n].reshape(batch, -1) for n in self.token_fields], 1).long()
            features.append(self.tokens(ids))
        return torch.cat(features, 1)


def _size(fields: list[ObsField]) -> int:
    return sum(f.size for f in fields)


class ObsNormalizer(nn.Module):
    """Running mean and variance of the vector fields of the observation; ``forward`` standardises them and
    clips to +-``clip`` (image and token fields pass unchanged).

    The statistics are buffers, so they travel with the weights: generation standardises with exactly the
    statistics of the policy version that acts. Training folds each batch in with ``merge(sums(obs))``
    (Chan et al.'s parallel update); until the first batch the transform is the identity.
    """

    def __init__(self, layout: ObsLayout, clip: float = 10.0, eps: float = 1e-8):
        super().__init__()
        mask, offset = torch.zeros(layout.size, dtype=torch.bool), 0
        for f in layout.fields:
            if f.kind == "vector":
                mask[offset:offset + f.size] = True
            offset += f.size
        self.register_buffer("mask", mask, persistent=False)
        self.register_buffer("mean", torch.zeros(layout.size))
        self.register_buffer("var", torch.ones(layout.size))
        self.register_buffer("count", torch.zeros((), dtype=torch.float64))
        self.clip, self.eps = clip, eps

    def forward(self, obs: torch.Tensor) -> torch.Tensor:
        z = ((obs - self.mean) / torch.sqrt(self.var + self.eps)).clamp(-self.clip, self.clip)
        return torch.where(self.mask, z, obs)

    def sums(self, obs: torch.Tensor | np.ndarray) -> np.ndarray:
        """[count, sum of x (D), sum of x**2 (D)] of a batch of flat observations (possibly none), float64:
        what ranks add up."""
        o = (obs.detach().cpu().numpy() if isinstance(obs, torch.Tensor) else np.asarray(obs))
        o = o.astype(np.float64).reshape(len(obs), self.mean.numel())
        return np.concatenate([[len(o)], o.sum(0), (o ** 2).sum(0)])

    @torch.no_grad()
    def merge(self, sums: np.ndarray) -> None:
        """Fold a batch (its ``sums``, possibly added over ranks) into the running statistics (Chan et al.)."""
        n, dim = float(sums[0]), self.mean.numel()
        if n == 0:
            return
        mean = sums[1:1 + dim] / n
        var = np.maximum(sums[1 + dim:] / n - mean ** 2, 0.0)
        count = self.count.item()
        total = count + n
        old_mean = self.mean.double().cpu().numpy()
        old_var = self.var.double().cpu().numpy() if count else np.zeros(dim)
        delta = mean - old_mean
        m2 = old_var * count + var * n + delta ** 2 * count * n / total
        self.mean.copy_(torch.from_numpy(old_mean + delta * n / total))
        self.var.copy_(torch.from_numpy(m2 / total))
        self.count.fill_(total)
