"""Observation layout: how one flat float32 observation vector splits into named parts.

Embodied observations are several things at once: a camera image, the robot's
proprioception, a language instruction. On the bus they travel as one flat
float32 vector per environment (one array per message, whatever the task);
the :class:`ObsLayout` says which slice is which, so a policy can route the
image to a conv encoder, the instruction tokens to an embedding table and the
rest to an MLP. Images are channel-first, scaled to [0, 1]; tokens are integer
ids stored as floats (exact below 2**24). A field read from uint8 pixels says so
(``ObsField.uint8``): its values are bytes / 255, and on the bus it travels as
those bytes (:meth:`ObsLayout.to_wire`), a quarter of the float32 size.

Instructions are tokenized by a word-hashing tokenizer the project owns (no
vocabulary file, nothing to download): lower-cased words, each mapped to one
of ``VOCAB_SIZE - 1`` ids by CRC32; id 0 is padding.
"""

from __future__ import annotations

import functools
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
    uint8: bool = False  # the values are bytes / 255 (an image read from uint8 pixels): uint8 on the bus

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

    # --- on the bus: uint8 fields as bytes --------------------------------------------------------------

    @functools.cached_property
    def _columns(self) -> tuple[np.ndarray, np.ndarray]:
        """Positions in the flat vector of the float fields' values and of the uint8 fields' values."""
        floats, raw, offset = [], [], 0
        for f in self.fields:
            (raw if f.uint8 else floats).append(np.arange(offset, offset + f.size))
            offset += f.size
        join = lambda parts: np.concatenate(parts) if parts else np.zeros(0, np.int64)  # noqa: E731
        return join(floats), join(raw)

    @property
    def byte_size(self) -> int:
        """Values of the uint8 fields: what travels as bytes."""
        return sum(f.size for f in self.fields if f.uint8)

    def to_wire(self, flat: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
        """Observations ``[B, *any shape of size]`` as the bus carries them: ``([B, size - byte_size]`` float32 of
        the other fields, ``[B, byte_size]`` uint8 of the uint8 fields``)``. Without uint8 fields, the
        observations unchanged and ``[B, 0]`` bytes."""
        batch = flat.shape[0]
        if not self.byte_size:
            return np.asarray(flat, np.float32), np.zeros((batch, 0), np.uint8)
        flat = flat.reshape(batch, self.size)
        floats, raw = self._columns
        with np.errstate(invalid="ignore"):  # a NaN pixel was counted and replaced before (ebrl.envs.guard)
            pixels = np.rint(np.clip(flat[:, raw], 0.0, 1.0) * 255.0).astype(np.uint8)
        return np.ascontiguousarray(flat[:, floats], np.float32), pixels

    def from_wire(self, floats: np.ndarray, pixels: np.ndarray) -> np.ndarray:
        """:meth:`to_wire`'s two arrays back as flat float32 observations ``[B, size]`` (pixels / 255); ValueError
        when their widths are not this layout's."""
        batch = floats.shape[0]
        floats = floats.reshape(batch, -1)
        if pixels.shape != (batch, self.byte_size) or floats.shape[1] != self.size - self.byte_size:
            raise ValueError(f"observations of {floats.shape[1]} float and {pixels.shape[-1]} byte values; the "
                             f"layout {self.describe()} has {self.size - self.byte_size} and {self.byte_size}")
        if not self.byte_size:
            return floats
        out = np.empty((batch, self.size), np.float32)
        float_cols, raw_cols = self._columns
        out[:, float_cols] = floats
        out[:, raw_cols] = np.divide(pixels, np.float32(255), dtype=np.float32)  # as the env side scaled them
        return out

    def to_dict(self) -> list[dict[str, Any]]:
        return [{"name": f.name, "kind": f.kind, "shape": list(f.shape), **({"uint8": True} if f.uint8 else {})}
                for f in self.fields]

    @classmethod
    def from_dict(cls, items: list[dict[str, Any]]) -> "ObsLayout":
        return cls(tuple(ObsField(d["name"], d["kind"], tuple(int(s) for s in d["shape"]), bool(d.get("uint8")))
                         for d in items))


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
