"""Check a decoded value against a type annotation; the one validator behind messages and config.

Supported annotations: ``int``, ``float`` (ints accepted), ``bool``, ``str``,
``Any``, ``list[T]``, ``dict[K, V]``, ``Literal[...]``, ``X | None`` and
``Annotated[np.ndarray, Array(dtype, ndim)]``. Errors name the path of the
offending value (``run.iterations``, ``Observation.obs``).
"""

from __future__ import annotations

import types
import typing
from dataclasses import dataclass
from typing import Annotated, Any, Literal, get_args, get_origin

import numpy as np


@dataclass(frozen=True)
class Array:
    """Annotation for a numpy array field: dtype and number of dimensions (None: any)."""

    dtype: str | None = None
    ndim: int | None = None


_NAMES = {str: "string", int: "integer", float: "number", bool: "boolean", list: "list", dict: "map"}


def describe(value: Any) -> str:
    text = repr(value)
    return f"{_NAMES.get(type(value), type(value).__name__)} {text if len(text) <= 40 else text[:37] + '...'}"


def check(value: Any, tp: Any, path: str, error: type[Exception]) -> Any:
    """Return ``value`` (floats widened from ints) if it matches ``tp``, else raise ``error`` naming ``path``."""
    origin = get_origin(tp)
    if tp is Any:
        return value
    if origin is Annotated:
        base, *extra = get_args(tp)
        spec = next((e for e in extra if isinstance(e, Array)), None)
        return _array(value, spec, path, error) if spec is not None else check(value, base, path, error)
    if origin in (types.UnionType, typing.Union):
        options = [a for a in get_args(tp) if a is not type(None)]
        if value is None and len(options) < len(get_args(tp)):
            return None
        problems = []
        for option in options:
            try:
                return check(value, option, path, error)
            except error as exc:
                problems.append(str(exc))
        raise error("; ".join(problems))
    if origin is Literal:
        if value not in get_args(tp):
            raise error(f"{path} = {value!r}: expected one of {', '.join(map(repr, get_args(tp)))}")
        return value
    if origin is list:
        if not isinstance(value, list):
            raise error(f"{path}: expected a list, got {describe(value)}")
        (item,) = get_args(tp)
        return [check(v, item, f"{path}[{i}]", error) for i, v in enumerate(value)]
    if origin is dict:
        if not isinstance(value, dict):
            raise error(f"{path}: expected a map, got {describe(value)}")
        key_tp, item = get_args(tp)
        return {check(k, key_tp, f"{path} key", error): check(v, item, f"{path}[{k!r}]", error)
                for k, v in value.items()}
    if tp is float:
        if isinstance(value, bool) or not isinstance(value, (int, float)):
            raise error(f"{path}: expected a number, got {describe(value)}")
        return float(value)
    if tp is int:
        if isinstance(value, bool) or not isinstance(value, int):
            raise error(f"{path}: expected an integer, got {describe(value)}")
        return value
    if tp is bool or tp is str:
        if not isinstance(value, tp):
            raise error(f"{path}: expected {'true or false' if tp is bool else 'a string'}, got {describe(value)}")
        return value
    raise TypeError(f"{path}: unsupported annotation {tp!r}")  # a bug in the declaring module, not bad input


def _array(value: Any, spec: Array, path: str, error: type[Exception]) -> np.ndarray:
    if not isinstance(value, np.ndarray):
        raise error(f"{path}: expected an array, got {describe(value)}")
    if spec.dtype is not None and value.dtype != np.dtype(spec.dtype):
        raise error(f"{path}: dtype {value.dtype}, expected {spec.dtype}")
    if spec.dtype is None and value.dtype.kind not in "biuf":
        raise error(f"{path}: dtype {value.dtype} is not numeric")
    if spec.ndim is not None and value.ndim != spec.ndim:
        raise error(f"{path}: {value.ndim} dimensions, expected {spec.ndim}")
    return value
