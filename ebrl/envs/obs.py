"""Observation layout: how one flat float32 observation vector splits into named parts.

Embodied observations are several things at once: a camera image, the robot's
proprioception, a language instruction. On the bus they travel as one flat
float32 vector per environment (one array per message, whatever the task);
the :class:`ObsLayout` says which slice is which, so a policy can route the
image to a conv encoder, the instruction tokens to an embedding table and the
rest to an MLP. Images are channel-first, scaled to [0, 1]; tokens are integer
ids stored as floats (exact below 2**24).

Instructions are tokenized by a word-hashing tokenizer the project owns (no
vocabulary file, nothing to download): lower-cased words, each mapped to one
of ``VOCAB_SIZE - 1`` ids by CRC32; id 0 is padding.
"""

from __future__ import annotations

import math
import re
import zlib
from dataclasses import dataclass
from typing import Any, Literal

import numpy as np

VOCAB_SIZE = 4096
INSTRUCTION_TOKENS = 16

FieldKind = Literal["vector", "image", "tokens"]


@dataclass(frozen=True)
class ObsField:
    name: str
    kind: FieldKind
    shape: tuple[int, ...]  # image: (C, H, W); vector and tokens: (n,)

    @property
    def size(self) -> int:
        return math.prod(self.shape)


@dataclass(frozen=True)
class ObsLayout:
    """Named slices of a flat observation vector, in order."""

    fields: tuple[ObsField, ...]

    def __post_init__(self) -> None:
        names = [f.name for f in self.fields]
        if not names or len(set(names)) != len(names):
            raise ValueError(f"an observation layout needs distinct field names, got {names}")

    @classmethod
    def vector(cls, size: int) -> "ObsLayout":
        """The plain case: the whole observation is one state vector."""
        return cls((ObsField("state", "vector", (int(size),)),))

    @classmethod
    def for_shape(cls, shape: tuple[int, ...]) -> "ObsLayout":
        """Layout of an environment that declares none: a 3-d Box is a channel-first image, anything else a vector."""
        if len(shape) == 3:
            return cls((ObsField("image", "image", tuple(int(s) for s in shape)),))
        return cls.vector(math.prod(shape))

    @property
    def size(self) -> int:
        return sum(f.size for f in self.fields)

    def of_kind(self, kind: FieldKind) -> list[ObsField]:
        return [f for f in self.fields if f.kind == kind]

    def split(self, flat: Any) -> dict[str, Any]:
        """Split observations ``[B, *any shape with size]`` (numpy array or torch tensor) into ``{name: [B, *shape]}``."""
        batch = flat.shape[0]
        flat = flat.reshape(batch, -1)
        if flat.shape[1] != self.size:
            raise ValueError(f"observation has {flat.shape[1]} values; the layout {self.describe()} has {self.size}")
        out, offset = {}, 0
        for f in self.fields:
            out[f.name] = flat[:, offset:offset + f.size].reshape(batch, *f.shape)
            offset += f.size
        return out

    def pack(self, parts: dict[str, np.ndarray]) -> np.ndarray:
        """One observation's parts (no batch dimension) as the flat float32 vector."""
        missing = [f.name for f in self.fields if f.name not in parts]
        if missing:
            raise ValueError(f"observation parts missing: {missing}")
        out = []
        for f in self.fields:
            part = np.asarray(parts[f.name], dtype=np.float32)
            if part.size != f.size:
                raise ValueError(f"observation part {f.name!r} has {part.size} values, layout says {f.shape}")
            out.append(part.ravel())
        return np.concatenate(out)

    def describe(self) -> str:
        return " + ".join(f"{f.name}:{f.kind}{list(f.shape)}" for f in self.fields)

    def to_dict(self) -> list[dict[str, Any]]:
        return [{"name": f.name, "kind": f.kind, "shape": list(f.shape)} for f in self.fields]

    @classmethod
    def from_dict(cls, items: list[dict[str, Any]]) -> "ObsLayout":
        return cls(tuple(ObsField(d["name"], d["kind"], tuple(int(s) for s in d["shape"])) for d in items))


_WORD = re.compile(r"[a-z0-9]+")


def tokenize(text: str, length: int = INSTRUCTION_TOKENS, vocab: int = VOCAB_SIZE) -> np.ndarray:
    """Instruction -> ``length`` token ids in [1, vocab) (0 pads; words beyond ``length`` are dropped)."""
    ids = [1 + zlib.crc32(w.encode()) % (vocab - 1) for w in _WORD.findall(text.lower())][:length]
    out = np.zeros(length, dtype=np.int64)
    out[:len(ids)] = ids
    return out


def sample_observations(layout: ObsLayout, n: int, rng: np.random.Generator | int = 0,
                        instruction: str = "lift the red cube") -> np.ndarray:
    """``n`` made-up flat observations of ``layout`` (timing a policy without its env: ``ebrl.autotune``, the
    benchmarks): vectors standard normal, images uniform in [0, 1], tokens the ``instruction``'s."""
    rng = np.random.default_rng(rng) if isinstance(rng, int) else rng
    fill = {"vector": lambda f: rng.normal(size=f.shape), "image": lambda f: rng.uniform(0.0, 1.0, f.shape),
            "tokens": lambda f: tokenize(instruction, f.size)}
    return np.stack([layout.pack({f.name: fill[f.kind](f) for f in layout.fields}) for _ in range(n)])
