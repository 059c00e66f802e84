"""Check a decoded value against a type annotation; the one validator behind messages and config.

Supported annotations: ``int``, ``float`` (ints accepted), ``bool``, ``str``,
``Any``, ``list[T]``, ``dict[K, V]``, ``Literal[...]``, ``X | None`` and
``Annotated[np.ndarray, Array(dtype, ndim)]``. Errors name the path of the
offending value (``run.iterations``, ``Observation.obs``). Any value may be checked -- a
decoded payload is an attacker's choice -- and the only exception for a mismatch is ``error``;
messages show a bounded summary of the value, however large or deep it is.
"""

from __future__ import annotations

import reprlib
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
_REPR = reprlib.Repr()  # keyword arguments only from Python 3.12
_REPR.maxlevel, _REPR.maxstring, _REPR.maxlong, _REPR.maxother = 2, 40, 40, 40
_REPR.maxtuple = _REPR.maxlist = _REPR.maxarray = _REPR.maxdict = _REPR.maxset = _REPR.maxfrozenset = 4


def describe(value: Any) -> str:
    """The kind of ``value`` and the start of its repr, in bounded time however large or deep it is."""
    return f"{_NAMES.get(type(value), type(value).__name__)} {_short(value)}"


def _short(value: Any) -> str:
    try:
        text = _REPR.repr(value)
    except Exception:  # a repr that fails (an int past Python's digit limit): the type says enough
        text = f"<{type(value).__name__}>"
    return text if len(text) <= 40 else text[:37] + "..."


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
    if origin is Literal:  # same type and equal: an array's == is elementwise, True == 1
        if not any(type(value) is type(option) and value == option for option in get_args(tp)):
            raise error(f"{path} = {_short(value)}: expected one of {', '.join(map(repr, get_args(tp)))}")
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
        return {check(k, key_tp, f"{path} key", error): check(v, item, f"{path}[{_short(k)}]", error)
                for k, v in value.items()}
    if tp is float:
        if isinstance(value, bool) or not isinstance(value, (int, float)):
            raise error(f"{path}: expected a number, got {describe(value)}")
        try:
            return float(value)
        except OverflowError:  # an int beyond float's range
            raise error(f"{path}: {describe(value)} is too large for a number") from None
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
