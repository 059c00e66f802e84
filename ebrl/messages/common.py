"""What every message type shares: the errors a receiver counts, the size limits, the field docstrings
(:func:`doc`) and the checks of counts, finite values and byte rows that the types' ``check`` methods use."""

from __future__ import annotations

from dataclasses import field
from typing import Any

import numpy as np

SCHEMA_VERSION = 1


class MessageError(ValueError):
    """A payload that is not a valid message of the expected type."""


class OversizedError(MessageError):
    """A payload over its message type's ``MAX_BYTES`` (counted as ``bus/oversized`` too)."""


KIB, MIB = 1 << 10, 1 << 20
CONTROL_MAX_BYTES = 64 * KIB  # stop, affinity, quota, GPU share: a few fields
DATA_MAX_BYTES = 256 * MIB  # a group's observations or one segment: camera images of many envs or steps
MAX_VERSION = 1 << 53  # policy and control versions beyond this are not counters (float64 loses them)
MAX_METRICS = 4096  # names in one stats report
MAX_TEXT = 4096  # characters of a free-text field (a reason, an event line)


def all_finite(name: str, *arrays: np.ndarray) -> None:
    for array in arrays:
        if array.dtype.kind == "f" and array.size and not np.isfinite(array).all():
            raise MessageError(f"{name}: a value is not finite (NaN or inf)")


def in_range(name: str, value: int, low: int = 0, high: int = MAX_VERSION) -> None:
    if not low <= value <= high:
        raise MessageError(f"{name} = {value}: outside [{low}, {high}]")


NO_BYTES = np.zeros((0, 0), np.uint8)  # a message's ``images`` when the observations have no uint8 fields


def byte_rows(name: str, images: np.ndarray, rows: int) -> None:
    """An ``images`` array holds a row per observation, or nothing at all."""
    if images.size and images.shape[0] != rows:
        raise MessageError(f"{name}: {images.shape[0]} rows of bytes for {rows} observations")


def doc(text: str, **kw: Any) -> Any:
    """A dataclass field with a docstring (used in ``schemas/`` and docs/reference/messages.md)."""
    return field(metadata={"doc": text}, **kw)
