"""The policy weights (train -> gen): a version whole, or in parts when it is large (``ebrl.weights``)."""

from __future__ import annotations

from dataclasses import dataclass
from typing import Annotated

import numpy as np

from ebrl.messages.common import MIB, all_finite, doc, in_range
from ebrl.typecheck import Array


@dataclass
class Weights:
    """Versioned policy weights (train -> gen)."""

    KEY = "ebrl/data/<run>/weights"
    version: int = doc("policy version; increases by one per update")
    params: dict[str, Annotated[np.ndarray, Array()]] = doc("state dict: parameter name -> array")
    created_at: float = doc("epoch seconds when train produced them")

    MAX_BYTES = 8 * MIB  # ebrl.weights sends a version of 4 MiB or more in parts

    def check(self) -> None:
        in_range("Weights.version", self.version)
        all_finite("Weights.params", *self.params.values())


@dataclass
class WeightsPart:
    """One part of a large weights version (train -> gen): a byte range of the version's arrays laid end to end,
    each array at a 64-byte aligned offset. Part ``index`` starts at ``index * part_bytes``; part 0 carries the
    manifest (names, dtypes, shapes, offsets). A receiver applies a version only once every part arrived."""

    KEY = "ebrl/data/<run>/weights/parts"
    version: int = doc("policy version; increases by one per update")
    index: int = doc("part number, 0 .. count - 1")
    count: int = doc("number of parts of this version")
    part_bytes: int = doc("length of every part but the last, which holds the rest")
    total_bytes: int = doc("length of the version's buffer")
    created_at: float = doc("epoch seconds when train produced the weights")
    data: Annotated[np.ndarray, Array("uint8", 1)] = doc("this part's bytes")
    names: list[str] = doc("part 0: parameter names, in buffer order; other parts: empty", default_factory=list)
    dtypes: list[str] = doc("part 0: numpy dtype string of each parameter (e.g. '<f4')", default_factory=list)
    shapes: list[list[int]] = doc("part 0: shape of each parameter", default_factory=list)
    offsets: list[int] = doc("part 0: byte offset of each parameter in the buffer", default_factory=list)

    MAX_BYTES = 8 * MIB  # ebrl.weights.PART_BYTES of data and part 0's manifest

    def check(self) -> None:
        in_range("WeightsPart.version", self.version)
        in_range("WeightsPart.count", self.count, 1, 1 << 20)
        in_range("WeightsPart.index", self.index, 0, self.count - 1)
        in_range("WeightsPart.part_bytes", self.part_bytes, 1, 64 * MIB)
        in_range("WeightsPart.total_bytes", self.total_bytes, 1, 1 << 40)
