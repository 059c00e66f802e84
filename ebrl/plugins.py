"""A class a config names: one EBRL registers, or a user's own as ``"pkg.module:Class"`` (``algo.name``, an
``env.id`` of a MuJoCo task)."""

from __future__ import annotations

import importlib
from typing import Any, Mapping


def named_class(field: str, name: str, registry: Mapping[str, str], base: type, error: type[Exception] = ValueError
                ) -> Any:
    """The subclass of ``base`` that ``name`` names: a key of ``registry`` (whose values are ``"module:Class"``) or
    ``"pkg.module:Class"`` itself, imported now. ``error`` (naming ``field``) where it is neither, does not import,
    or is not a subclass of ``base``."""
    target = registry.get(name, name)
    module, _, attr = target.partition(":")
    kind = f"{base.__module__}.{base.__qualname__}"
    if not attr:
        raise error(f"{field} = {name!r}: expected one of {', '.join(map(repr, registry))} or \"pkg.module:Class\" "
                    f"(an {kind} subclass)")
    try:
        cls = getattr(importlib.import_module(module), attr)
    except (ImportError, AttributeError) as exc:
        raise error(f"{field} = {name!r}: cannot load {target}: {exc}") from None
    if not (isinstance(cls, type) and issubclass(cls, base)):
        raise error(f"{field} = {name!r}: {target} is not an {kind} subclass")
    return cls
